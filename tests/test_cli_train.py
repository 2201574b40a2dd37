"""`dbh train` option checks (no training runs here; smoke runs live in test_models_*)."""
import pytest

pytest.importorskip("torch")
from typer.testing import CliRunner  # noqa: E402

from monodbh.cli.main import app  # noqa: E402


def test_augment_preset_is_checked(tmp_path):
    r = CliRunner().invoke(app, ["train", "tree", "--out", str(tmp_path / "r"), "--augment", "strong"])
    assert r.exit_code == 2 and "--augment" in r.output
    r = CliRunner().invoke(app, ["train", "segmenter", "--out", str(tmp_path / "r"), "--augment", "wild"])
    assert r.exit_code == 2 and "strong" in r.output
    assert not (tmp_path / "r").exists()


def test_augment_presets_are_valid_configs():
    from monodbh.models.training.common import AUGMENT_PRESETS, AugmentConfig

    assert set(AUGMENT_PRESETS) >= {"default", "strong"}
    assert AUGMENT_PRESETS["default"] == AugmentConfig()
    assert AUGMENT_PRESETS["strong"].hue_deg > AugmentConfig().hue_deg


def test_crop_is_for_the_rope_finder_only(tmp_path):
    r = CliRunner().invoke(app, ["train", "rope_verifier", "--out", str(tmp_path / "r"), "--crop", "96"])
    assert r.exit_code == 2 and "--crop" in r.output
    assert not (tmp_path / "r").exists()


def test_kinds_are_the_networks_names(tmp_path):
    from monodbh.cli.train_cmd import KINDS

    assert KINDS == ("segmenter", "depth", "tree", "stem_base", "stem_edge", "rope_verifier", "rope_finder")
    r = CliRunner().invoke(app, ["train", "ropeseg", "--out", str(tmp_path / "r")])
    assert r.exit_code == 2 and "rope_finder" in r.output
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("kind,module,fn,key", [("stem_base", "stem_base", "train_stem_base", "lr"),
                                                ("stem_edge", "stem_edge", "train_stem_edge", "lr"),
                                                ("tree", "tree", "train_tree", "lr_g")])
def test_lr_reaches_the_kinds_config(tmp_path, monkeypatch, kind, module, fn, key):
    import importlib

    seen = {}
    mod = importlib.import_module(f"monodbh.models.training.{module}")
    monkeypatch.setattr(mod, fn, lambda *a, **kw: seen.update(kw) or {"step": 0})
    r = CliRunner().invoke(app, ["train", kind, "--out", str(tmp_path / "r"), "--steps", "5", "--lr", "5e-4"])
    assert r.exit_code == 0, r.output
    assert seen[key] == 5e-4 and ({"lr", "lr_g"} - {key}).isdisjoint(seen)


def test_lr_must_be_positive(tmp_path):
    r = CliRunner().invoke(app, ["train", "stem_base", "--out", str(tmp_path / "r"), "--lr", "0"])
    assert r.exit_code == 2 and "--lr" in r.output


def test_export_recipe_is_checked_before_any_work(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    r = CliRunner().invoke(app, ["export", str(run), "--recipe", "u8s8_qdq_all", "--recipe", "int4_magic"])
    assert r.exit_code == 2 and "int4_magic" in r.output and "u8s8_qdq_conv_gemm" in r.output
    assert list(run.iterdir()) == []

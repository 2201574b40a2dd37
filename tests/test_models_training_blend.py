"""Weight-space blending of a fine-tuned run with its starting weights (`dbh train-blend`)."""
import json

import pytest

torch = pytest.importorskip("torch")

from monodbh.models.training.blend import blend_run, blend_state_dicts  # noqa: E402
from monodbh.models.training.common import RunDir  # noqa: E402
from monodbh.models.runtime.common import MODELS_DIR  # noqa: E402

START = MODELS_DIR / "stem_base_int8.onnx"


def test_blend_state_dicts_is_the_straight_line():
    a = {"w": torch.zeros(3), "n": torch.tensor(1)}
    b = {"w": torch.tensor([1.0, 2.0, 4.0]), "n": torch.tensor(7)}
    out = blend_state_dicts(a, b, 0.25)
    assert torch.allclose(out["w"], torch.tensor([0.25, 0.5, 1.0])) and int(out["n"]) == 7
    assert torch.equal(blend_state_dicts(a, b, 0.0)["w"], a["w"])
    with pytest.raises(ValueError, match="alpha"):
        blend_state_dicts(a, b, 1.5)
    with pytest.raises(ValueError, match="keys"):
        blend_state_dicts({"v": torch.zeros(3)}, b, 0.5)
    with pytest.raises(ValueError, match="shape"):
        blend_state_dicts({"w": torch.zeros(2), "n": torch.tensor(1)}, b, 0.5)


def _tuned_run(tmp_path, frozen_bn=True):
    """A run folder as a warm-started stem-base fine-tune leaves it: the shipped weights moved."""
    from monodbh.models.modeling import registry
    from monodbh.models.training.onnx_init import state_dict_from_onnx

    sd, _ = state_dict_from_onnx(START, registry.build("stem_base", "base"))
    g = torch.Generator().manual_seed(0)
    tuned = {k: (v + torch.randn(v.shape, generator=g) if v.is_floating_point() and "running" not in k else v)
             for k, v in sd.items()}
    run = RunDir(tmp_path / "tuned").mkdir()
    torch.save({"kind": "stem_base", "size": "base", "step": 10, "model": tuned, "optim": {}}, run.checkpoint_path)
    run.write_config({"kind": "stem_base", "size": "base", "steps": 10,
                      "init_weights": {"file": str(START), "frozen_bn": frozen_bn, "from_step": 6}})
    return run, sd, tuned


def test_blend_run_writes_an_exportable_run_halfway(tmp_path):
    run, start, tuned = _tuned_run(tmp_path)
    info = blend_run(run.path, tmp_path / "blend", 0.5)
    out = RunDir(tmp_path / "blend")
    ck = out.load_checkpoint()
    assert ck["kind"] == "stem_base" and ck["step"] == 10 and "optim" not in ck
    for k, v in ck["model"].items():
        if v.is_floating_point():
            assert torch.allclose(v, 0.5 * (start[k] + tuned[k]), atol=1e-5), k
    cfg = json.loads(out.config_path.read_text())
    assert cfg["blend"] == info and info["alpha"] == 0.5 and len(info["start_sha256"]) == 64
    assert cfg["init_weights"]["from_step"] == 6
    with pytest.raises(FileExistsError):
        blend_run(run.path, tmp_path / "blend", 0.5)


def test_blend_needs_frozen_batchnorm(tmp_path):
    run, _, _ = _tuned_run(tmp_path, frozen_bn=False)
    with pytest.raises(ValueError, match="frozen BatchNorm"):
        blend_run(run.path, tmp_path / "blend", 0.5)
    assert not (tmp_path / "blend").exists()

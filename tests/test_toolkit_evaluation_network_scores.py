"""The per-network scorecard's ratio (issue 26's 1.25x bound) and its command-line checks."""
import pytest

from monodbh.toolkit.evaluation.network_scores import FIGURES, main, ratio


def test_ratio_is_how_many_times_worse():
    assert ratio(0.2, 0.25, True) == pytest.approx(1.25)     # an error grew by a quarter
    assert ratio(0.8, 0.64, False) == pytest.approx(1.25)    # a score shrank by a fifth
    assert ratio(0.8, 0.9, False) < 1 and ratio(0.3, 0.2, True) < 1
    assert ratio(0.0, 0.1, True) == float("inf")


def test_every_network_has_a_figure():
    from monodbh.models.runtime.common import load_manifest
    from monodbh.models.export.cli_impl import MODELS_DIR
    shipped = set(load_manifest(MODELS_DIR / "manifest.json")["models"]) - {"rope_verifier"}
    assert {k for k, _, _ in FIGURES} == shipped


def test_missing_folder_is_an_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "nope")])
    assert e.value.code == 2 and "nope: not a folder" in capsys.readouterr().err

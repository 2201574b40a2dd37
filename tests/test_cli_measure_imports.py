"""Measuring a photo loads only the measuring path: no evaluation, training, export, scene
generator or calibration code (checked in a fresh interpreter, after a real ``dbh measure``)."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "toolkit" / "examples"

#: modules (and their submodules) that measuring a photo must not import
NOT_ON_THE_MEASURING_PATH = (
    "monodbh.toolkit.evaluation", "monodbh.models.training", "monodbh.models.export",
    "monodbh.models.synthetic", "monodbh.models.modeling", "monodbh.calib.board",
    "monodbh.calib.calibration", "monodbh.calib.coverage", "monodbh.calib.pose",
    "monodbh.calib.debug", "monodbh.cli.calibrate_cmd", "monodbh.cli.eval_cmd",
    "monodbh.cli.train_cmd", "monodbh.cli.synth_cmd", "monodbh.toolkit.cluster", "torch", "trimesh",
    "onnx", "distributed", "dask",
)

_SCRIPT = """
import json, sys
sys.argv = ["dbh", "measure", {photo!r}, "--calib", {calib!r}, "--json"]
from monodbh.cli.main import main
try:
    main()
except SystemExit as exc:
    code = exc.code
else:
    code = 0
sys.stdout.flush()
print("MODULES " + json.dumps({{"code": code, "modules": sorted(sys.modules)}}))
"""


def _measure_in_fresh_interpreter():
    script = _SCRIPT.format(photo=str(EXAMPLES / "example.jpg"), calib=str(EXAMPLES / "cam.yaml"))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    line = [s for s in out.stdout.splitlines() if s.startswith("MODULES ")]
    assert line, out.stderr[-2000:]
    return out.stdout, json.loads(line[-1][len("MODULES "):])


def _offenders(modules):
    return [m for m in modules if any(m == f or m.startswith(f + ".") for f in NOT_ON_THE_MEASURING_PATH)]


@pytest.mark.slow
def test_measuring_a_photo_loads_only_the_measuring_path():
    stdout, got = _measure_in_fresh_interpreter()
    assert got["code"] == 0
    first = json.loads(stdout.splitlines()[0])
    assert first["error"] is None and first["dbh_cm"] > 0           # it really measured
    assert "monodbh.toolkit.pipeline" in got["modules"]
    assert "monodbh.models.runtime.segmenter" in got["modules"]
    assert not _offenders(got["modules"]), _offenders(got["modules"])


def test_the_check_names_submodules_and_spares_look_alikes():
    assert _offenders(["monodbh.toolkit.evaluation.synth_eval", "monodbh.calib.board", "torch.nn"]) == [
        "monodbh.toolkit.evaluation.synth_eval", "monodbh.calib.board", "torch.nn"]
    assert _offenders(["monodbh.calib.camera", "monodbh.toolkit.pipeline", "torchvisionx"]) == []


def test_importing_the_public_api_is_light():
    code = ("import sys, monodbh.toolkit as t; assert 'monodbh.toolkit.pipeline' not in sys.modules; "
            "from monodbh.toolkit import measure_photo, Session, MeasureResult, MeasureConfig; "
            "print(measure_photo.__module__, Session.__module__, MeasureResult.__module__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["monodbh.toolkit.pipeline", "monodbh.toolkit.pipeline", "monodbh.toolkit.result"]

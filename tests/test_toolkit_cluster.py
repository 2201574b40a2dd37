"""dbh measure --scheduler: a batch on a local Dask cluster of 2 worker processes gives the rows of a
local run (CSV, JSON lines, report), one Session per worker, and clear errors when it cannot run."""
import csv
import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

distributed = pytest.importorskip("distributed", reason="Dask's distributed is the optional extra monodbh[cluster]")

from monodbh.cli.main import app  # noqa: E402
from monodbh.toolkit.cluster import iter_cluster_results, window  # noqa: E402
from monodbh.toolkit.result import MeasureResult  # noqa: E402

HERE = Path(__file__).resolve().parent
EXAMPLES = HERE.parent / "toolkit" / "examples"
FN = "test_toolkit_cluster:pid_measure"
SESSION = "test_toolkit_cluster:CountingSession"


class CountingSession:
    """A stand-in session that leaves one file per creation in ``$MONODBH_TEST_SESSIONS``."""

    def __init__(self, models_dir=None):
        folder = Path(os.environ["MONODBH_TEST_SESSIONS"])
        self.pid = os.getpid()
        (folder / f"session_{self.pid}_{id(self)}").touch()


def pid_measure(path, camera, *, session=None, **kw):
    """Deterministic per photo; records which worker process and session measured it."""
    name = Path(path).name
    if "bad" in name:
        return MeasureResult(photo=path, error=f"{path}: no red rope found", timings_ms={"total": 1.0})
    k = int(name.split("_")[1].split(".")[0])
    return MeasureResult(photo=path, dbh_cm=20.0 + k / 7, dbh_sigma_cm=1.5, distance_m=3.0 + k / 11,
                         scale_source="stem_base", flags=[], timings_ms={"total": float(session.pid)})


def broken_session(models_dir=None):
    raise RuntimeError("no models on this worker")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A scheduler with 2 worker processes (1 thread each) that can import this test module."""
    sessions = tmp_path_factory.mktemp("sessions")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PYTHONPATH", str(HERE), prepend=os.pathsep)
        mp.setenv("MONODBH_TEST_SESSIONS", str(sessions))
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                      dashboard_address=None, silence_logs=40) as lc:
            yield lc.scheduler_address, sessions


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        for k in [k for k in r if k.startswith("timing")]:
            r.pop(k)
    return rows


def _example_photos(folder: Path) -> list[Path]:
    """The bundled example and variants that measure differently: mirrored, cropped, recompressed,
    and a file that is not a photo."""
    folder.mkdir()
    im = Image.open(EXAMPLES / "example.jpg")
    w, h = im.size
    out = [folder / "a_example.jpg", folder / "b_mirrored.jpg", folder / "c_cropped.jpg",
           folder / "d_q70.jpg", folder / "e_broken.jpg"]
    im.save(out[0], quality=95)
    im.transpose(Image.Transpose.FLIP_LEFT_RIGHT).save(out[1], quality=95)
    im.crop((w // 16, 0, w, h)).resize((w, h)).save(out[2], quality=95)
    im.save(out[3], quality=70)
    out[4].write_bytes(b"not a jpeg at all")
    return out


def test_real_batch_on_two_workers_is_the_local_run(cluster, tmp_path):
    address, _ = cluster
    photos = _example_photos(tmp_path / "photos")
    runner = CliRunner()
    base = ["measure", *map(str, photos), "--calib", str(EXAMPLES / "cam.yaml")]
    here = runner.invoke(app, [*base, "--csv", str(tmp_path / "local.csv"), "--json"])
    there = runner.invoke(app, [*base, "--csv", str(tmp_path / "dask.csv"), "--json", "--scheduler", address,
                                "--report", str(tmp_path / "dask.html")])
    assert here.exit_code == there.exit_code == 1, (here.output[-2000:], there.output[-2000:])
    local, dask = _rows(tmp_path / "local.csv"), _rows(tmp_path / "dask.csv")
    assert [r["photo"] for r in dask] == [str(p) for p in photos]
    assert local == dask
    assert sum(bool(r["dbh_cm"]) for r in dask) == 4 and "e_broken.jpg" in dask[4]["error"]
    assert len({r["dbh_cm"] for r in dask[:4]}) > 1          # the variants really measure differently
    html = (tmp_path / "dask.html").read_text()
    assert html.count('class="thumb"') >= 4 and "e_broken.jpg" in html


def test_one_session_per_worker_and_rows_in_order(cluster, tmp_path):
    address, sessions = cluster
    for f in sessions.iterdir():
        f.unlink()
    photos = tmp_path / "photos"
    photos.mkdir()
    names = [f"p_{k:03d}.jpg" for k in range(40)] + ["bad_1.jpg"]
    for n in names:
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(photos / n)
    r = CliRunner().invoke(app, ["measure", str(photos), "--calib", str(EXAMPLES / "cam.yaml"),
                                 "--measure-fn", FN, "--session-factory", SESSION, "--scheduler", address,
                                 "--csv", str(tmp_path / "out.csv")])
    assert r.exit_code == 1, r.output[-2000:]
    with open(tmp_path / "out.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [Path(x["photo"]).name for x in rows] == sorted(names)
    created = sorted(f.name for f in sessions.iterdir())
    pids = {n.split("_")[1] for n in created}
    assert len(created) == len(pids) <= 2, created           # at most one session per worker process
    workers = {str(int(json.loads(x["timings_ms"])["total"])) for x in rows if x["dbh_cm"]}
    assert workers <= pids and len(workers) == 2              # both workers measured, each with its session


def test_iter_cluster_results_streams_in_input_order(cluster, tmp_path):
    from monodbh.toolkit.batch import Backend, Job

    address, _ = cluster
    jobs = [Job(index=k, photo=str(tmp_path / f"p_{k:03d}.jpg"), camera=None) for k in range(30)]
    got = list(iter_cluster_results(jobs, Backend(measure=FN, session=SESSION), address))
    assert [g.photo for g in got] == [j.photo for j in jobs]
    assert window(2) == 8 and window(10) == 40


def test_broken_session_on_the_workers_stops_the_batch(cluster, tmp_path):
    address, _ = cluster
    photo = tmp_path / "p_001.jpg"
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(photo)
    r = CliRunner().invoke(app, ["measure", str(photo), str(photo.with_name("p_002.jpg")), "--calib",
                                 str(EXAMPLES / "cam.yaml"), "--measure-fn", FN,
                                 "--session-factory", "test_toolkit_cluster:broken_session",
                                 "--scheduler", address])
    assert r.exit_code == 1, r.output                          # as a local run: nothing measured
    assert "no models on this worker" in r.output and "Traceback" not in r.output


def test_unreachable_scheduler_is_one_line(tmp_path, monkeypatch):
    import monodbh.toolkit.cluster as cl

    monkeypatch.setattr(cl, "CONNECT_TIMEOUT_S", 2)
    photo = tmp_path / "p_001.jpg"
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(photo)
    r = CliRunner().invoke(app, ["measure", str(photo), str(photo), "--calib", str(EXAMPLES / "cam.yaml"),
                                 "--scheduler", "tcp://127.0.0.1:9"])
    assert r.exit_code == 1, r.output
    assert "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in r.output and "Traceback" not in r.output


def test_scheduler_refuses_workers(tmp_path):
    r = CliRunner().invoke(app, ["measure", str(EXAMPLES / "example.jpg"), "--calib", str(EXAMPLES / "cam.yaml"),
                                 "--scheduler", "tcp://127.0.0.1:9", "-j", "2"])
    assert r.exit_code == 2 and "--scheduler" in r.output

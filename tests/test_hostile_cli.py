"""Hostile input to ``dbh measure``, ``dbh depth`` and ``dbh reconstruct``, as a user would bring it.

Every case runs the real command in a fresh process, in a folder of its own holding its inputs
(generated here: ``tests/hostile_inputs.py``), and asserts:

* the exit status;
* the one-line message (``error: ...`` on stderr, or the row's ``error`` in ``--json`` output)
  naming the file and the problem;
* no traceback, no ``internal error``, no library warning text;
* every file that was there before is unchanged (bytes, mode and modification time);
* the process's peak memory (``ru_maxrss`` of the child) under 1.5 GB.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import stat
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import pytest

import hostile_inputs as H

MAX_RSS_BYTES = 1.5 * 2**30
_RUN_DBH = "import sys; from monodbh.cli.main import main; sys.argv[0] = 'dbh'; main()"
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


@dataclass
class Ran:
    code: int
    out: str
    err: str
    rss_bytes: int
    rows: list = field(default_factory=list)

    def error_lines(self) -> list[str]:
        return [l for l in self.err.splitlines() if l.startswith("error:")]


def run_dbh(args, cwd: Path, umask: int = 0o022, timeout: float = 240) -> Ran:
    """``dbh ARGS`` in a new process (``cwd``); its exit status, output and peak memory."""
    out_p, err_p = cwd.parent / f".{cwd.name}.out", cwd.parent / f".{cwd.name}.err"
    with open(out_p, "wb") as fo, open(err_p, "wb") as fe:
        env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "PYTHONWARNINGS": ""}
        proc = subprocess.Popen([sys.executable, "-c", _RUN_DBH, *args], cwd=cwd, stdout=fo, stderr=fe,
                                env=env, preexec_fn=lambda: os.umask(umask))
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        except BaseException:
            proc.kill()
            raise
        proc.returncode = os.waitstatus_to_exitcode(status)
    out = out_p.read_bytes().decode("utf-8", "replace")
    err = err_p.read_bytes().decode("utf-8", "replace")
    rows = []
    for line in out.splitlines():
        if line.startswith("{"):
            try:
                rows.append(json.loads(line))
            except ValueError:
                pass
    return Ran(proc.returncode, out, err, usage.ru_maxrss * 1024, rows)


def snapshot(root: Path) -> dict:
    """Every file under ``root``: bytes digest, mode and mtime (symlinks by their target text)."""
    snap = {}
    for dirpath, dirnames, files in os.walk(os.fsencode(root)):
        for name in files + [n for n in dirnames if os.path.islink(os.path.join(dirpath, n))]:
            p = os.path.join(dirpath, name)
            st = os.lstat(p)
            if stat.S_ISLNK(st.st_mode):
                snap[p] = ("link", os.readlink(p))
            elif stat.S_ISREG(st.st_mode):
                with open(p, "rb") as f:
                    snap[p] = (hashlib.sha256(f.read()).hexdigest(), st.st_mode, st.st_mtime_ns)
            else:
                snap[p] = ("special", st.st_mode)
    return snap


def check_common(r: Ran, before: dict, root: Path) -> None:
    text = r.out + r.err
    assert "Traceback" not in text, text[-3000:]
    assert "internal error" not in text, text[-3000:]
    assert not re.search(r"\w+Warning\b|warnings\.warn|\.py:\d+:", text), text[-3000:]
    # decoders' own messages (libjpeg prints its warnings to the process's stderr) never leak;
    # the one-line errors may quote them
    leaked = [l for l in r.err.splitlines() if not l.startswith(("error: ", "warning: "))
              and re.search(r"Corrupt JPEG data|Premature end of JPEG|libpng|libjpeg|libtiff", l)]
    assert not leaked, leaked
    assert r.rss_bytes < MAX_RSS_BYTES, f"peak memory {r.rss_bytes / 2**20:.0f} MiB"
    after = snapshot(root)
    changed = [os.fsdecode(p) for p, v in before.items() if after.get(p) != v]
    assert not changed, f"inputs changed or removed: {changed}"


# -- the cases -------------------------------------------------------------------------------------
@dataclass
class Case:
    """One hostile run: ``setup(folder) -> argv`` (paths relative to the folder), the expected
    exit status and a regular expression the error must match (on one line)."""
    name: str
    setup: Callable[[Path], list]
    code: int
    message: Optional[str]
    check: Optional[Callable[[Path, Ran], None]] = None
    umask: int = 0o022
    root_skip: bool = False


CASES: list[Case] = []


def case(name, code, message=None, check=None, **kw):
    def deco(setup):
        CASES.append(Case(name, setup, code, message, check, **kw))
        return setup
    return deco


def _rel(d: Path, p) -> str:
    return os.fsdecode(os.path.relpath(os.fsencode(p), os.fsencode(d)))


def measure_args(d: Path, photo, cam=None, *extra) -> list:
    cam = cam or H.good_camera(d)
    return ["measure", _rel(d, photo), "--calib", _rel(d, cam), *extra,
            *([] if "--json" in extra else ["--json"])]


# photos: each must be refused (or measured) with the photo named
PHOTO_EXPECT = {
    "empty": (1, r"empty\.jpg: .*empty"),
    "text": (1, r"notes\.jpg: .*not an image"),
    "html": (1, r"page\.jpg: .*not an image"),
    "junk": (1, r"junk\.jpg: .*not an image"),
    "truncated_jpeg": (1, r"truncated\.jpg: .*truncated"),
    "truncated_png": (1, r"truncated\.png: .*(truncated|corrupt)"),
    "corrupt_middle": (1, r"corrupt_middle\.jpg: .*corrupt"),
    "header_108mp": (1, r"claims_108mp\.jpg: .*(corrupt|truncated)"),
    "png_bomb": (1, r"bomb\.png: .*too large"),
    "png_bad_crc": (1, r"bad_crc\.png: .*(corrupt|CRC)"),
    "tiff_huge_header": (1, r"huge\.tif: .*(too large|corrupt|truncated)"),
    "1px": (1, r"one_pixel\.png: .*too small"),
    "10px": (1, r"ten_pixels\.jpg: .*too small"),
    "thin_strip": (1, r"strip\.png: .*too small"),
    "animated_gif": (1, r"animated\.gif: .*animated"),
    "rotated_no_exif": (0, None),
    "rotated_ccw_no_exif": (1, r"sideways_ccw\.jpg: no red rope found .*on its side .*rotate it upright"),
    "png_renamed_jpg": (0, None),
    "exif_orientation_garbage": (0, None),
    "cmyk": (0, None),
    "other_aspect": (1, r"cropped\.jpg: .*aspect"),
}
def _check_sideways(d: Path, r: Ran) -> None:
    """Measured (the networks find upright "trunks" in it too) but flagged for the user."""
    assert "photo_maybe_sideways" in r.rows[0]["flags"], r.rows[0]


for _name, (_code, _msg) in PHOTO_EXPECT.items():
    case(f"photo-{_name}", _code, _msg, check=_check_sideways if _name == "rotated_no_exif" else None)(
        lambda d, _f=H.PHOTOS[_name]: measure_args(d, _f(d), None, "--json"))


@case("photo-missing", 1, r"not_here\.jpg: no such file")
def _(d):
    return measure_args(d, d / "not_here.jpg")


@case("photo-fifo", 1, r"pipe\.jpg: .*not a regular file")
def _(d):
    os.mkfifo(d / "pipe.jpg")
    return measure_args(d, d / "pipe.jpg")


@case("photo-symlink-loop", 1, r"loop\.jpg: .*(symbolic links|no such file|cannot read)")
def _(d):
    os.symlink("loop.jpg", d / "loop.jpg")
    return measure_args(d, d / "loop.jpg")


@case("photo-dangling-symlink", 1, r"gone\.jpg: no such file")
def _(d):
    os.symlink("deleted.jpg", d / "gone.jpg")
    return measure_args(d, d / "gone.jpg")


@case("photo-unreadable", 1, r"locked\.jpg: .*permission denied", root_skip=True)
def _(d):
    p = H.good_photo(d, "locked.jpg")
    p.chmod(0)
    return measure_args(d, p)


@case("photo-empty-folder", 2, r"no photos found in empty_dir")
def _(d):
    (d / "empty_dir").mkdir()
    return measure_args(d, d / "empty_dir")


# camera files: each refused with the file named
CAM_EXPECT = {
    "missing": r"no_such_cam\.yaml: no such file",
    "empty": r"empty\.yaml: .*empty",
    "binary": r"binary\.yaml: .*not a text file",
    "xml": r"cam\.xml\.yaml: .*XML",
    "not_mapping": r"list\.yaml: .*mapping",
    "no_matrix": r"no_matrix\.yaml: .*camera_matrix",
    "width_inf": r"width_inf\.yaml: .*image_width",
    "width_1e300": r"width_1e300\.yaml: .*image_width",
    "width_huge_int": r"width_huge\.yaml: .*image_width",
    "size_absurd": r"size_absurd\.yaml: .*image_(width|height)|size",
    "deep_nesting": r"deep\.yaml: .*nest",
    "alias_bomb_name": r"bomb_name\.yaml: .*alias",
    "alias_bomb_time": r"bomb_time\.yaml: .*alias",
    "alias_bomb_dt": r"bomb_dt\.yaml: .*alias",
    "alias_bomb_ros_model": r"bomb_ros\.yaml: .*alias",
    "alias_bomb_width": r"bomb_width\.yaml: .*alias",
    "nan_focal": r"nan_focal\.yaml: .*(NaN|finite)",
    "tiny_fov": r"tiny_fov\.yaml: .*field of view",
    "huge_fov": r"huge_fov\.yaml: .*field of view",
    "principal_point_outside": r"pp_outside\.yaml: .*principal point",
    "aspect_absurd": r"fx_fy\.yaml: .*(fx|fy|aspect|pixel)",
    "negative_focal": r"neg_focal\.yaml: .*(focal|camera_matrix)",
    "distortion_folds": r"folds\.yaml: .*distortion",
    "distortion_nan": r"dist_nan\.yaml: .*(NaN|finite)",
    "matrix_wrong_size": r"matrix_2x3\.yaml: .*(3x3|values)",
    "pose_nan": r"pose_nan\.yaml: .*(camera_height_m|pose|finite|NaN)",
    "pose_absurd": r"pose_high\.yaml: .*camera_height_m",
    "marker_width_absurd": r"marker_huge\.yaml: .*marker_width_mm",
    "marker_width_text": r"marker_text\.yaml: .*marker_width_mm",
    "huge_file": r"huge\.yaml: .*(too large|MB|KB|bytes)",
    "directory": r"cam_dir\.yaml: .*directory",
}
for _name, _msg in CAM_EXPECT.items():
    case(f"camera-{_name}", 1, _msg)(
        lambda d, _f=H.CAMERAS[_name]: measure_args(d, H.good_photo(d), _f(d)))


# flags
FLAG_EXPECT = {
    "pick-text": (["--pick", "left"], 2, r"--pick"),
    "pick-negative": (["--pick", "-5,3"], 2, r"--pick"),
    "pick-nan": (["--pick", "nan,3"], 2, r"--pick"),
    "pick-outside": (["--pick", "99999,5"], 1, r"tree\.jpg: .*--pick 99999,5 is outside the 1280x960 px photo"),
    "base-outside": (["--base", "5000,90000"], 1, r"tree\.jpg: .*--base 5000,90000 is outside the 1280x960 px photo"),
    "base-inf": (["--base", "inf,3"], 2, r"--base"),
    "base-three-numbers": (["--base", "1,2,3"], 2, r"--base"),
    "rope-mm-zero": (["--rope-mm", "0"], 2, r"--rope-mm"),
    "rope-mm-nan": (["--rope-mm", "nan"], 2, r"--rope-mm"),
    "rope-mm-inf": (["--rope-mm", "inf"], 2, r"--rope-mm"),
    "rope-mm-text": (["--rope-mm", "thick"], 2, r"--rope-mm"),
    "workers-zero": (["--workers", "0"], 2, r"--workers"),
    "workers-text": (["--workers", "many"], 2, r"--workers"),
    "unknown-option": (["--frobnicate"], 2, r"frobnicate"),
}
for _name, (_extra, _code, _msg) in FLAG_EXPECT.items():
    case(f"flag-{_name}", _code, _msg)(
        lambda d, _e=_extra: measure_args(d, H.good_photo(d), None, *_e))


@case("flag-base-two-photos", 2, r"--base is a pixel of one photo")
def _(d):
    H.good_photo(d, "b.jpg")
    return measure_args(d, H.good_photo(d), None, "b.jpg", "--base", "600,900")


@case("flag-models-dir-empty", 1, r"no_models: .*(no model|manifest)")
def _(d):
    (d / "no_models").mkdir()
    return measure_args(d, H.good_photo(d), None, "--models-dir", "no_models")


@case("flag-models-dir-missing", 1, r"not_there: .*(no such folder|no such|does not exist)")
def _(d):
    return measure_args(d, H.good_photo(d), None, "--models-dir", "not_there")


@case("flag-models-dir-file", 1, r"models\.txt: .*(not a folder|directory)")
def _(d):
    (d / "models.txt").write_text("x")
    return measure_args(d, H.good_photo(d), None, "--models-dir", "models.txt")


# output paths
@case("out-csv-under-file", 1, r"blocker/out\.csv: .*(not a folder|not a directory)")
def _(d):
    (d / "blocker").write_text("a file, not a folder")
    return measure_args(d, H.good_photo(d), None, "--csv", "blocker/out.csv")


@case("out-dir-under-file", 1, r"blocker/out: .*(not a folder|not a directory)")
def _(d):
    (d / "blocker").write_text("a file, not a folder")
    return measure_args(d, H.good_photo(d), None, "--out-dir", "blocker/out")


@case("out-dir-is-file", 1, r"blocker: .*(not a folder|not a directory)")
def _(d):
    (d / "blocker").write_text("a file, not a folder")
    return measure_args(d, H.good_photo(d), None, "--out-dir", "blocker")


@case("out-csv-is-folder", 1, r"a_folder: .*(is a folder|is a directory)")
def _(d):
    (d / "a_folder").mkdir()
    return measure_args(d, H.good_photo(d), None, "--csv", "a_folder")


@case("out-csv-is-the-photo", 2, r"--csv tree\.jpg is one of the inputs")
def _(d):
    return measure_args(d, H.good_photo(d), None, "--csv", "tree.jpg")


@case("out-csv-is-the-photo-by-other-path", 2, r"is one of the inputs")
def _(d):
    (d / "sub").mkdir()
    return measure_args(d, H.good_photo(d), None, "--csv", "sub/../tree.jpg")


@case("out-csv-is-the-camera", 2, r"--csv cam\.yaml is one of the inputs")
def _(d):
    return measure_args(d, H.good_photo(d), H.good_camera(d), "--csv", "cam.yaml")


@case("out-csv-hardlink-to-photo", 2, r"is one of the inputs")
def _(d):
    p = H.good_photo(d)
    os.link(p, d / "link.csv")
    return measure_args(d, p, None, "--csv", "link.csv")


@case("out-dir-overwrites-photo", 2, r"would overwrite the input .*a_overlay\.png")
def _(d):
    """In the photos' own folder, photo ``a.jpg`` has the overlay name of... ``a_overlay.png`` is
    also a photo given: measuring ``a.jpg`` there would overwrite it."""
    (d / "photos").mkdir()
    H.good_photo(d / "photos", "a.jpg")
    im = H._example_image()
    im.save(d / "photos" / "a_overlay.png")
    return ["measure", "photos", "--calib", _rel(d, H.good_camera(d)), "--out-dir", "photos"]


def _check_outputs_beside(d: Path, r: Ran) -> None:
    assert (d / "photos" / "a_overlay.png").is_file() and (d / "photos" / "results.jsonl").is_file()


@case("out-dir-is-photo-folder", 0, None, check=_check_outputs_beside)
def _(d):
    (d / "photos").mkdir()
    H.good_photo(d / "photos", "a.jpg")
    return ["measure", "photos", "--calib", _rel(d, H.good_camera(d)), "--out-dir", "photos"]


NON_UTF8 = b"tr\xe9e_\xff.jpg"                      # Latin-1 e-acute and a stray byte


def _check_non_utf8(d: Path, r: Ran) -> None:
    csv_text = (d / "out.csv").read_text("utf-8")
    assert "tr\\xe9e_\\xff.jpg" in csv_text, csv_text
    rows = [json.loads(l) for l in (d / "out" / "results.jsonl").read_text("utf-8").splitlines()]
    assert rows[0]["photo"].endswith("tr\\xe9e_\\xff.jpg") and rows[0]["error"] is None
    names = os.listdir(os.fsencode(d / "out"))
    assert b"tr\xe9e_\xff_overlay.png" in names and b"tr\xe9e_\xff_tree.ply" in names, names


@case("out-non-utf8-photo-name", 0, None, check=_check_non_utf8)
def _(d):
    H.good_photo(d, NON_UTF8)
    return ["measure", os.fsdecode(NON_UTF8), "--calib", _rel(d, H.good_camera(d)), "--csv", "out.csv",
            "--out-dir", "out", "--json"]


def _check_non_utf8_dir(d: Path, r: Ran) -> None:
    names = os.listdir(os.fsencode(d / os.fsdecode(b"r\xe9sultats")))
    assert b"tree_overlay.png" in names and b"summary.json" in names, names


@case("out-non-utf8-out-dir", 0, None, check=_check_non_utf8_dir)
def _(d):
    return measure_args(d, H.good_photo(d), None, "--out-dir", os.fsdecode(b"r\xe9sultats"))


LONG_STEM = "t" * 245


def _check_long_name(d: Path, r: Ran) -> None:
    row = r.rows[0]
    assert row["error"] is None
    written = os.listdir(d / "out")
    overlays = [n for n in written if n.endswith("_overlay.png")]
    clouds = [n for n in written if n.endswith("_tree.ply")]
    assert len(overlays) == 1 and len(clouds) == 1 and all(len(n.encode()) <= 255 for n in written), written


@case("out-249-char-name", 0, None, check=_check_long_name)
def _(d):
    return measure_args(d, H.good_photo(d, LONG_STEM + ".jpg"), None, "--out-dir", "out", "--json")


def _check_modes(expect: int):
    def check(d: Path, r: Ran) -> None:
        for p in [d / "out.csv", *(d / "out").iterdir()]:
            assert stat.S_IMODE(p.stat().st_mode) == expect, (p, oct(p.stat().st_mode))
    return check


case("out-umask-022", 0, None, check=_check_modes(0o644), umask=0o022)(
    lambda d: measure_args(d, H.good_photo(d), None, "--out-dir", "out", "--csv", "out.csv"))
case("out-umask-077", 0, None, check=_check_modes(0o600), umask=0o077)(
    lambda d: measure_args(d, H.good_photo(d), None, "--out-dir", "out", "--csv", "out.csv"))


# batches: bad photos reported and skipped, the good ones measured, rows in order
def _batch_folder(d: Path) -> Path:
    b = d / "batch"
    b.mkdir()
    H.good_photo(b, "a_good.jpg")
    for f in (H.photo_corrupt_middle, H.photo_1px, H.photo_animated_gif, H.photo_text,
              H.photo_truncated_jpeg, H.photo_png_bomb):
        f(b)
    H.good_photo(b, "z_good.jpg")
    return b


def _check_batch(d: Path, r: Ran) -> None:
    from monodbh.toolkit.batch import PHOTO_EXTENSIONS

    by = {Path(x["photo"]).name: x for x in r.rows}
    given = sorted(n for n in os.listdir(d / "batch") if Path(n).suffix.lower() in PHOTO_EXTENSIONS)
    assert sorted(by) == given and "animated.gif" not in given, by.keys()   # a folder's photos only
    assert by["a_good.jpg"]["error"] is None and by["z_good.jpg"]["error"] is None
    for name, want in [("corrupt_middle.jpg", "corrupt"), ("one_pixel.png", "too small"),
                       ("notes.jpg", "not an image"), ("truncated.jpg", "truncated"),
                       ("bomb.png", "too large")]:
        err = by[name]["error"] or ""
        assert name in err and want in err, (name, err)
    assert [Path(x["photo"]).name for x in r.rows] == given
    csv_lines = (d / "out.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + len(r.rows)


case("batch-mixed", 1, None, check=_check_batch)(
    lambda d: ["measure", _rel(d, _batch_folder(d)), "--calib", _rel(d, H.good_camera(d)), "--json",
               "--csv", "out.csv"])
case("batch-mixed-2-workers", 1, None, check=_check_batch)(
    lambda d: ["measure", _rel(d, _batch_folder(d)), "--calib", _rel(d, H.good_camera(d)), "--json",
               "--csv", "out.csv", "--workers", "2"])


# dbh depth and dbh reconstruct
@case("depth-1px", 1, r"one_pixel\.png: .*too small")
def _(d):
    return ["depth", _rel(d, H.photo_1px(d)), "--calib", _rel(d, H.good_camera(d)), "--out-dir", "out"]


@case("depth-corrupt", 1, r"corrupt_middle\.jpg: .*corrupt")
def _(d):
    return ["depth", _rel(d, H.photo_corrupt_middle(d)), "--calib", _rel(d, H.good_camera(d)), "-o", "out"]


@case("depth-out-dir-under-file", 1, r"blocker/out: .*(not a folder|not a directory)")
def _(d):
    (d / "blocker").write_text("x")
    return ["depth", _rel(d, H.good_photo(d)), "--calib", _rel(d, H.good_camera(d)), "-o", "blocker/out"]


@case("depth-overwrites-input", 2, r"would overwrite the input .*tree_depth\.npy")
def _(d):
    H.good_photo(d)
    (d / "tree_depth.npy").write_bytes(b"not really")
    return ["depth", "tree.jpg", "tree_depth.npy", "--calib", _rel(d, H.good_camera(d)), "-o", "."]


@case("depth-bad-camera", 1, r"tiny_fov\.yaml: .*field of view")
def _(d):
    return ["depth", _rel(d, H.good_photo(d)), "--calib", _rel(d, H.cam_tiny_fov(d)), "-o", "out"]


@case("reconstruct-1px", 1, r"one_pixel\.png: .*too small")
def _(d):
    return ["reconstruct", _rel(d, H.photo_1px(d)), "--calib", _rel(d, H.good_camera(d)), "-o", "s.ply"]


@case("reconstruct-out-under-file", 1, r"blocker/s\.ply: .*(not a folder|not a directory)")
def _(d):
    (d / "blocker").write_text("x")
    return ["reconstruct", _rel(d, H.good_photo(d)), "--calib", _rel(d, H.good_camera(d)), "-o", "blocker/s.ply"]


@case("reconstruct-base-outside", 1, r"tree\.jpg: .*--base 9000,9000 is outside")
def _(d):
    return ["reconstruct", _rel(d, H.good_photo(d)), "--calib", _rel(d, H.good_camera(d)), "-o", "s.ply",
            "--base", "9000,9000"]


@case("reconstruct-animated", 1, r"animated\.gif: .*animated")
def _(d):
    return ["reconstruct", _rel(d, H.photo_animated_gif(d)), "--calib", _rel(d, H.good_camera(d)), "-o", "s.ply"]


# -- the test ---------------------------------------------------------------------------------------
def _message_lines(r: Ran) -> list[str]:
    """The error messages the user sees: ``error:`` lines on stderr and the rows' ``error``."""
    return [l[len("error: "):] for l in r.error_lines()] + [x["error"] for x in r.rows if x.get("error")]


@pytest.mark.parametrize("c", CASES, ids=[c.name for c in CASES])
def test_hostile(c: Case, tmp_path: Path) -> None:
    if c.root_skip and IS_ROOT:
        pytest.skip("running as root: file permissions do not apply")
    d = tmp_path / "case"
    d.mkdir()
    args = c.setup(d)
    before = snapshot(d)
    r = run_dbh(args, d, umask=c.umask)
    assert r.code == c.code, (r.code, r.err[-2000:], r.out[-2000:])
    check_common(r, before, d)
    msgs = _message_lines(r)
    if c.message is not None:
        assert msgs, (r.err, r.out)
        assert all("\n" not in m and len(m) < 400 for m in msgs), msgs
        assert any(re.search(c.message, m) for m in msgs), (c.message, msgs, r.err[-1500:])
    elif c.code == 0:
        assert not msgs, msgs
    if c.check is not None:
        c.check(d, r)


def test_enough_cases() -> None:
    kinds = {c.name.split("-")[0] for c in CASES}
    assert len(CASES) >= 60 and kinds >= {"photo", "camera", "flag", "out", "batch", "depth", "reconstruct"}


def main() -> None:
    """``python tests/test_hostile_cli.py``: every case as a table (exit status, peak memory, the
    message), and the totals the acceptance asks for."""
    import tempfile

    worst, failed = 0, []
    print(f"{'case':42s} {'exit':>4s} {'MiB':>6s}  message")
    for c in CASES:
        if c.root_skip and IS_ROOT:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp) / "case"
            d.mkdir()
            args = c.setup(d)
            before = snapshot(d)
            r = run_dbh(args, d, umask=c.umask)
            try:
                assert r.code == c.code
                check_common(r, before, d)
                if c.check:
                    c.check(d, r)
                ok = True
            except AssertionError:
                ok, _ = False, failed.append(c.name)
            msg = (_message_lines(r) or [""])[0]
            worst = max(worst, r.rss_bytes)
            print(f"{c.name:42s} {r.code:4d} {r.rss_bytes / 2**20:6.0f}  {'' if ok else 'FAIL '}{msg[:90]}")
    print(f"{len(CASES)} cases, {len(failed)} failed {failed}; worst peak memory {worst / 2**20:.0f} MiB")


if __name__ == "__main__":
    main()

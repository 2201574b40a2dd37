"""toolkit.outputs.atomic: whole files or none, the old file kept on failure, no temporary left."""
import os
import stat

import numpy as np
import pytest

from monodbh.toolkit.outputs.atomic import atomic_open, atomic_path, atomic_write_bytes, atomic_write_text


def _files(folder):
    return sorted(p.name for p in folder.iterdir())


def test_text_and_bytes_written_whole_in_a_new_folder(tmp_path):
    p = atomic_write_text(tmp_path / "a" / "b" / "r.json", "é\r\nx\n")
    assert p == tmp_path / "a" / "b" / "r.json"
    assert p.read_bytes() == "é\r\nx\n".encode("utf-8")          # UTF-8, newlines as given
    atomic_write_bytes(p, b"\x00\x01")
    assert p.read_bytes() == b"\x00\x01" and _files(p.parent) == ["r.json"]
    # a new file's mode honours the umask, as open() would give (not mkstemp's 0600)
    mask = os.umask(0o022)
    os.umask(mask)
    assert stat.S_IMODE(os.stat(p).st_mode) == 0o666 & ~mask


class Boom(Exception):
    pass


@pytest.mark.parametrize("exc", [Boom, KeyboardInterrupt])
def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, exc):
    p = tmp_path / "summary.json"
    atomic_write_text(p, "old\n")
    with pytest.raises(exc):
        with atomic_open(p, "w") as f:
            f.write("half of the new")
            raise exc()
    assert p.read_text() == "old\n" and _files(tmp_path) == ["summary.json"]
    with pytest.raises(exc):
        with atomic_path(p) as tmp:
            with open(tmp, "w") as f:
                f.write("half")
            raise exc()
    assert p.read_text() == "old\n" and _files(tmp_path) == ["summary.json"]


def test_a_failed_first_write_leaves_nothing(tmp_path):
    with pytest.raises(Boom):
        with atomic_open(tmp_path / "new.npy", "wb") as f:
            f.write(b"\x93NUMPY")
            raise Boom()
    assert _files(tmp_path) == []


def test_writers_by_file_object_and_by_path(tmp_path):
    with atomic_open(tmp_path / "d.npy", "wb") as f:
        np.save(f, np.arange(3, dtype=np.float32))
    assert np.load(tmp_path / "d.npy").tolist() == [0.0, 1.0, 2.0]
    with atomic_path(tmp_path / "c.txt") as tmp:
        assert os.path.dirname(tmp) == str(tmp_path) and os.path.exists(tmp)
        with open(tmp, "w") as f:
            f.write("by name")
        assert not (tmp_path / "c.txt").exists()             # replaced only when the block ends
    assert (tmp_path / "c.txt").read_text() == "by name" and _files(tmp_path) == ["c.txt", "d.npy"]
    with pytest.raises(ValueError):
        with atomic_open(tmp_path / "x", "a"):
            pass

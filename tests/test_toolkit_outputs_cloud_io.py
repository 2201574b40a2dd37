"""toolkit.outputs.cloud_io: PLY/LAS round trips, formats CloudCompare reads, atomic writes, errors."""
import numpy as np
import pytest

from monodbh.toolkit.outputs.cloud_io import CloudFileError, read_cloud, write_cloud
from monodbh.toolkit.result import PointCloud


def _cloud(n=500, seed=0):
    rng = np.random.default_rng(seed)
    return PointCloud((rng.normal(size=(n, 3)) * [3, 2, 8] + [0, 0, 10]).astype(np.float32),
                      rng.integers(0, 256, (n, 3)).astype(np.uint8), rng.integers(0, 6, n).astype(np.int32))


def test_ply_round_trip_binary_le(tmp_path):
    c = _cloud()
    p = write_cloud(tmp_path / "a" / "scene.PLY", c)
    head = p.read_bytes()[:400]
    assert b"format binary_little_endian 1.0" in head
    for prop in (b"property float x", b"property uchar red", b"property int tree_id"):
        assert prop in head
    d = read_cloud(p)
    assert np.array_equal(d.xyz, c.xyz) and np.array_equal(d.rgb, c.rgb) and np.array_equal(d.tree_id, c.tree_id)
    assert d.tree_id.dtype == np.int32 and d.rgb.dtype == np.uint8


def test_las_round_trip_tree_id_rgb16(tmp_path):
    import laspy

    c = _cloud()
    p = write_cloud(tmp_path / "scene.las", c)
    las = laspy.read(str(p))
    assert las.header.point_format.id in (2, 7) and np.allclose(las.header.scales, 0.001)
    assert "tree_id" in las.point_format.extra_dimension_names
    assert int(np.asarray(las.red).max()) > 255  # 16-bit colours
    assert np.array_equal(np.asarray(las.classification) == 5, c.tree_id > 0)
    d = read_cloud(p)
    assert np.abs(d.xyz - c.xyz).max() <= 0.0006
    assert np.array_equal(d.rgb, c.rgb) and np.array_equal(d.tree_id, c.tree_id)


def test_the_trunk_flag_round_trips_where_known_and_reads_none_where_not(tmp_path):
    import laspy

    c = _cloud()
    c.trunk = np.random.default_rng(3).random(len(c)) < 0.3
    for ext in ("ply", "las"):
        d = read_cloud(write_cloud(tmp_path / f"t.{ext}", c))
        assert d.trunk is not None and np.array_equal(d.trunk, c.trunk)
        assert read_cloud(write_cloud(tmp_path / f"u.{ext}", _cloud())).trunk is None
    assert b"property uchar trunk" in (tmp_path / "t.ply").read_bytes()[:500]
    assert b"trunk" not in (tmp_path / "u.ply").read_bytes()[:500]
    assert "trunk" in laspy.read(str(tmp_path / "t.las")).point_format.extra_dimension_names
    # a cloud joined from parts with and without the flag does not claim it
    both = PointCloud.concat([c, _cloud(10)])
    assert both.trunk is None and len(both) == 510
    assert PointCloud.concat([c, c]).trunk.sum() == 2 * c.trunk.sum()
    with pytest.raises(ValueError, match="trunk"):
        write_cloud(tmp_path / "bad.ply", PointCloud(c.xyz, c.rgb, c.tree_id, c.trunk[:5]))


def test_empty_cloud_and_missing_colours(tmp_path):
    for ext in ("ply", "las"):
        write_cloud(tmp_path / f"e.{ext}", PointCloud.concat([]))
        assert len(read_cloud(tmp_path / f"e.{ext}")) == 0
    xyz = np.zeros((3, 3), np.float32)
    write_cloud(tmp_path / "n.ply", PointCloud(xyz, np.zeros((0, 3), np.uint8), np.zeros(0, np.int32)))
    assert read_cloud(tmp_path / "n.ply").tree_id.tolist() == [0, 0, 0]


def test_errors_and_atomicity(tmp_path):
    c = _cloud(10)
    with pytest.raises(CloudFileError, match="unknown point-cloud extension '.xyz'"):
        write_cloud(tmp_path / "s.xyz", c)
    with pytest.raises(CloudFileError, match="no such file"):
        read_cloud(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_text("not a ply")
    with pytest.raises(CloudFileError, match="cannot read PLY"):
        read_cloud(tmp_path / "junk.ply")
    bad = PointCloud(np.full((2, 3), np.nan, np.float32), np.zeros((2, 3), np.uint8), np.zeros(2, np.int32))
    write_cloud(tmp_path / "keep.ply", c)
    with pytest.raises(ValueError):
        write_cloud(tmp_path / "keep.ply", bad)
    assert len(read_cloud(tmp_path / "keep.ply")) == 10
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []

"""toolkit.evaluation.synth_samples: a dbh synth folder's listing, cameras and true values."""
import json

import numpy as np
import pytest

from monodbh.toolkit.evaluation.synth_samples import (camera_from_meta, gt_dbh_cm, gt_rope_px, list_synth_samples,
                                                      read_ground_truth, true_rope_diameter_m)


def test_gt_rope_px_from_a_sample_record():
    meta = {"roped_tree": 2, "K": [[1000.0, 0, 0], [0, 1000.0, 0], [0, 0, 1]], "rope": {"tube_diameter_m": 0.008},
            "trees": [{"id": 1, "bh_point_cam": [0, 0, 3.0], "r_bh_m": 0.1},
                      {"id": 2, "bh_point_cam": [0, 0, 4.1], "r_bh_m": 0.1}]}
    assert gt_rope_px(meta) == pytest.approx(2.0)
    assert gt_rope_px({"roped_tree": None, "trees": []}) is None


def test_listing_camera_and_ground_truth(tmp_path):
    meta = {"width": 40, "height": 30, "K": [[35.0, 0, 20], [0, 35.0, 15], [0, 0, 1]], "dist": [0.1, 0, 0, 0, 0],
            "roped_tree": 2, "rope": {"tube_diameter_m": 0.008}, "trees": [{"id": 1, "dbh_m": 0.2}, {"id": 2, "dbh_m": 0.25}]}
    for i in (4, 1, 7):
        (tmp_path / f"{i:06d}.json").write_text(json.dumps(meta))
        (tmp_path / f"{i:06d}.jpg").write_bytes(b"x")
    z = np.zeros((30, 40), np.float32)
    arrays = dict(depth=z + 2, semantic=z.astype(np.uint8), instance=z.astype(np.uint16), rope=z > 0, z1=z, z2=z)
    np.savez(tmp_path / "000004.npz", **arrays)
    (tmp_path / "000009.json").write_text("{}")                                  # no photo: not a sample
    assert list_synth_samples(tmp_path) == [1, 4, 7] and list_synth_samples(tmp_path, need_npz=True) == [4]
    cam = camera_from_meta(meta)
    assert cam.image_size == (40, 30) and cam.fx == 35.0 and cam.dist[0] == pytest.approx(0.1) and cam.name == "synthetic"
    assert camera_from_meta({**meta, "dist": None}).dist.tolist() == [0.0] * 5
    gt = read_ground_truth(tmp_path / "000004.jpg")
    assert set(gt) == set(arrays) | {"meta"} and gt["meta"] == meta and float(gt["depth"][0, 0]) == 2.0
    with pytest.raises(OSError):
        read_ground_truth(tmp_path / "000001.jpg")
    assert gt_dbh_cm(meta) == pytest.approx(25.0) and gt_dbh_cm({**meta, "roped_tree": None}) is None
    assert true_rope_diameter_m(meta) == 0.008 and true_rope_diameter_m({"rope": None}) is None

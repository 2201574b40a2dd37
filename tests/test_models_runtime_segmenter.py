"""The segmenter's runtime: the predictor on a tiny exported segmenter, the panoptic merge."""
import numpy as np
import pytest

from monodbh.calib.errors import MonodbhError
from monodbh.models.runtime import common
from monodbh.models.runtime.segmenter import Segmenter, SegmentationResult, panoptic_merge


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    from monodbh.models.export import export_onnx
    from monodbh.models.modeling import build

    m = build("segmenter", "tiny")
    p = tmp_path_factory.mktemp("rt") / "segmenter.onnx"
    export_onnx(m, m.spec, p)
    return p


def test_segmenter_predict_shapes(tiny_model):
    seg = Segmenter(tiny_model)
    rgb = np.random.default_rng(0).integers(0, 255, (48, 80, 3), dtype=np.uint8)
    res = seg.predict(rgb, score_threshold=0.0, overlap_threshold=0.0)
    assert isinstance(res, SegmentationResult)
    assert res.semantic.shape == (48, 80) and res.instance.shape == (48, 80)
    assert res.tree_masks.ndim == 3 and res.tree_masks.shape[1:] == (48, 80)
    assert res.tree_scores.shape == (res.tree_masks.shape[0],)
    assert res.classes == ("sky", "ground", "other_vegetation", "tree", "other")
    for m in res.stuff_masks.values():
        assert m.shape == (48, 80) and m.dtype == bool
    assert res.instance.max() == res.n_trees and res.tree_masks.sum(0).max() <= 1
    res2 = seg.predict(rgb, size=(40, 30), score_threshold=0.0, overlap_threshold=0.0)
    assert res2.semantic.shape == (30, 40) and res2.size == (40, 30)
    cls, msk = seg.raw(rgb)
    assert cls.shape == (8, 6) and msk.shape == (8, 16, 16)


def test_panoptic_merge_greedy():
    cls = np.full((3, 6), -9.0, np.float32)
    cls[:, 5] = 9.0
    cls[0, 5], cls[0, 3] = -9.0, 9.0    # tree
    cls[1, 5], cls[1, 0] = -9.0, 9.0    # sky
    msk = np.full((3, 8, 8), -9.0, np.float32)
    msk[0, 3:, 2:4] = 9.0               # tree below the sky
    msk[1, :3] = 9.0
    msk[2] = 9.0                        # no-object query: ignored
    out = panoptic_merge(cls, msk, (8, 8))
    labels = sorted(s["label"] for s in out["segments"])
    assert labels == [0, 3]
    tree = next(s for s in out["segments"] if s["label"] == 3)
    assert (out["panoptic"] == tree["id"]).sum() == 10
    # a segment that loses more than 20 % of its own mask to a better one is dropped
    msk[1, :4] = 9.0
    out = panoptic_merge(cls, msk, (8, 8))
    assert sorted(s["label"] for s in out["segments"]) == [0, 3]
    cls[1, 0] = 1.0                     # sky less confident: loses the overlap, 30/32 kept
    out = panoptic_merge(cls, msk, (8, 8), score_threshold=0.3)
    assert sorted(s["label"] for s in out["segments"]) == [0, 3]
    msk[1, :6] = 9.0
    out = panoptic_merge(cls, msk, (8, 8), score_threshold=0.3, overlap_threshold=0.9)  # 42/48
    assert [s["label"] for s in out["segments"]] == [3]
    # merged at a working resolution, returned at the requested one
    big = panoptic_merge(cls, msk, (800, 800), score_threshold=0.3, work_max_side=64)
    small = panoptic_merge(cls, msk, (64, 64), score_threshold=0.3, work_max_side=None)
    assert big["panoptic"].shape == (800, 800)
    assert np.array_equal(big["panoptic"][::25, ::25][:, :], small["panoptic"][::2, ::2])


def test_no_shipped_segmenter_is_user_error():
    with pytest.raises(MonodbhError, match="no shipped 'segmenter'"):
        Segmenter(manifest={"models": {}})


def test_segmenter_from_manifest_entry(tiny_model, tmp_path, monkeypatch):
    monkeypatch.setattr(common, "MODELS_DIR", tiny_model.parent)
    seg = Segmenter(manifest={"models": {"segmenter": {"file": tiny_model.name}}})
    assert seg.spec["kind"] == "segmenter" and seg.input_shape("image") == (1, 3, 64, 64)


def test_tile_weights_cross_fade_without_seams():
    from monodbh.models.runtime.segmenter import tile_boxes, tile_weight
    H, W = 90, 120                                   # tiles of 60 px, 30 apart: exact halves
    total = np.zeros((H, W), np.float32)
    for box in tile_boxes(H, W, 0.5):
        y0, y1, x0, x1 = box
        w = tile_weight(box, H, W)
        assert w.shape == (y1 - y0, x1 - x0) and w.min() > 0 and w.max() <= 1.0
        total[y0:y1, x0:x1] += w
    # where tiles overlap by half, the weights add up to one: a constant map blends to itself
    # and each tile fades out where its neighbour takes over, with no step at a tile's end
    assert np.allclose(total, 1.0, atol=1e-5)
    blended = np.zeros((H, W), np.float32)
    for i, box in enumerate(tile_boxes(H, W, 0.5)):  # each tile says a different constant
        y0, y1, x0, x1 = box
        blended[y0:y1, x0:x1] += tile_weight(box, H, W) * i
    blended /= total
    assert np.abs(np.diff(blended, axis=1)).max() < 0.2 and np.abs(np.diff(blended, axis=0)).max() < 0.2

"""Stem-edge network: ground-truth labels, ONNX export, training smoke run, hooks (the runtime:
test_models_runtime_stem_edge)."""
import json

import numpy as np
import pytest
import torch

from monodbh.models.modeling import build
from monodbh.models.runtime.stem_edge import PATCH_COLS_PER_W, PATCH_H, PATCH_W


def fake_edge_sample(seed=0, W=240, H=200, dist=4.0, r=0.2, cam_h=1.3, x_m=0.0, blocker_m=None):
    """A level camera ``cam_h`` m up; one vertical round stem of radius ``r`` at ``dist`` m ahead
    (``x_m`` to the right), bright on a dark background far behind. ``blocker_m``: a post 1 m
    from the camera whose left border is that far right of the line of sight to the stem's axis."""
    rng = np.random.default_rng(seed)
    f, cx, cy = 200.0, W / 2 - 0.5, H / 2 - 0.5
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    depth = np.full((H, W), 30.0)
    X = (u - cx) / f                                   # ray slope; the stem's axis at (x_m, dist)
    # the ray x = X z hits the circle (x - x_m)^2 + (z - dist)^2 = r^2 where its distance < r
    a = 1 + X * X
    b = -2 * (x_m * X + dist)
    c = x_m * x_m + dist * dist - r * r
    disc = b * b - 4 * a * c
    on = disc >= 0
    z = np.where(on, (-b - np.sqrt(np.clip(disc, 0, None))) / (2 * a), 0.0)
    depth = np.where(on, z, depth)
    rgb = rng.integers(20, 50, (H, W, 3)).astype(np.uint8)
    rgb[on] = (150, 120, 90)
    if blocker_m is not None:
        post = X >= x_m / dist + blocker_m
        depth[post] = 1.0
        rgb[post] = (40, 160, 40)
    tree = {"id": 1, "dbh_m": 2 * r, "r_bh_m": r, "position_world": [x_m, dist, 0.0], "axis_world": [0, 0, 1],
            "e1_world": [1, 0, 0], "e2_world": [0, 1, 0], "axis_ratio": 1.0, "ellipse_phase_rad": 0.0,
            "harmonics": [], "taper": 0.0, "flare": 0.0, "distance_m": dist}
    meta = {"K": [[f, 0, cx], [0, f, cy], [0, 0, 1]], "dist": [0.0] * 5, "width": W, "height": H,
            "R_world_from_cam": [[1, 0, 0], [0, 0, 1], [0, -1, 0]], "t_world_from_cam": [0, 0, cam_h],
            "trees": [tree], "roped_tree": 1}
    edges_x = cx + f * np.tan(np.arctan2(x_m, dist) + np.array([-1, 1]) * np.arcsin(r / np.hypot(x_m, dist)))
    return {"rgb": rgb, "depth": depth.astype(np.float32), "meta": meta}, edges_x


def test_ground_truth_edges_are_the_silhouette_tangents():
    from monodbh.models.training.stem_edge import StemEdgeTrainConfig, stem_edges_truth, tree_patches

    s, edges_x = fake_edge_sample(x_m=0.3)
    c, along, edges, z = stem_edges_truth(s["meta"], s["meta"]["trees"][0], 1.3)
    assert np.allclose(along, (0, 1), atol=1e-6) and z == pytest.approx(4.0)
    assert (c[0] + edges) == pytest.approx(edges_x, abs=0.02)
    ex = tree_patches(s, None, StemEdgeTrainConfig(), 1)
    assert len(ex) == 1 and ex[0]["roped"]
    width = edges_x[1] - edges_x[0]
    # the exact patch is centred between the edges and as wide as the stem: edges at 1/4 and 3/4
    assert ex[0]["cols"] == pytest.approx([PATCH_W / 4 - 0.5, 3 * PATCH_W / 4 - 0.5], abs=0.05)
    p = ex[0]["patch"][PATCH_H // 2, :, 0].astype(float)
    assert p[PATCH_W // 2] > 120 and p[5] < 60 and p[-5] < 60
    # jittered patches keep the label on the true edges (their own columns)
    exj = tree_patches(s, np.random.default_rng(0), StemEdgeTrainConfig(), 4)
    assert len(exj) == 4
    for e in exj:
        w_cols = e["cols"][1] - e["cols"][0]
        assert 0.5 * PATCH_COLS_PER_W < w_cols < 1.6 * PATCH_COLS_PER_W
    assert width > 10


def test_an_edge_hidden_by_a_nearer_object_is_no_example():
    from monodbh.models.training.stem_edge import StemEdgeTrainConfig, tree_patches

    s, _ = fake_edge_sample(blocker_m=0.03)            # the post covers the stem's right edge (at 0.05)
    assert tree_patches(s, None, StemEdgeTrainConfig(), 1) == []
    s, _ = fake_edge_sample(blocker_m=0.3)             # a post well clear of the stem
    assert len(tree_patches(s, None, StemEdgeTrainConfig(), 1)) == 1


def test_stem_edge_onnx_matches_torch(tmp_path):
    from monodbh.models.export.onnx_io import export_onnx

    torch.manual_seed(0)
    g = build("stem_edge", "tiny").eval()
    assert g(torch.randn(2, 4, PATCH_H, PATCH_W)).shape == (2, 2, PATCH_W)
    res = export_onnx(g, g.spec, tmp_path / "stem_edge.onnx", check=True, atol=1e-4)
    assert max(res["max_abs_err"].values()) < 1e-4


def test_train_stem_edge_smoke_resume_and_hooks(tmp_path):
    from monodbh.models.modeling import get_spec
    from monodbh.models.training.common import ListSource, calibration_inputs, evaluate_kind
    from monodbh.models.training.stem_edge import edge_metrics, train_stem_edge

    data = [fake_edge_sample(i, dist=3.0 + i)[0] for i in range(3)]
    opts = dict(size="tiny", batch_size=4, jitters=2, val_n=1, threads=1, warmup_steps=1, log_every=1,
                verbose=False)
    r = train_stem_edge(str(tmp_path / "a"), 2, data, stop_at=1, **opts)
    assert r["step"] == 1 and r["bank"] == 4                 # 2 training samples x 2 jitters
    r = train_stem_edge(str(tmp_path / "a"), 2, data, resume=True, verbose=False)
    assert r["step"] == 2 and {"width_median_pct", "width_p90_pct", "score"} <= set(r["val"])
    cfg = json.loads((tmp_path / "a" / "config.json").read_text())
    assert cfg["kind"] == "stem_edge" and cfg["train_indices"] == 2
    spec = get_spec("stem_edge", "tiny")
    src = ListSource(data)
    feeds = calibration_inputs("stem_edge", 2, 0, spec, src)
    assert feeds and feeds[0]["patch"].shape == (1, 4, PATCH_H, PATCH_W)
    g = build("stem_edge", "tiny").eval()

    def predict(f):
        with torch.no_grad():
            return {"logits": g(torch.from_numpy(f["patch"])).numpy()}

    m = evaluate_kind("stem_edge", predict, 2, 0, spec, src)
    assert spec.metric == "score" and 0.0 <= m["score"] <= 1.0
    # metrics: exact edges score 1; a right edge 4 columns out on a 64-column stem is 6 % wide
    z = np.full((1, 2, PATCH_W), -30.0)
    z[0, 0, 32] = z[0, 1, 96] = 5.0
    assert edge_metrics(z, np.array([[32.0, 96.0]]))["score"] == 1.0
    z2 = np.full((1, 2, PATCH_W), -30.0)
    z2[0, 0, 32] = z2[0, 1, 100] = 5.0
    m2 = edge_metrics(z2, np.array([[32.0, 96.0]]))
    assert m2["score"] == 0.0 and m2["width_median_pct"] == pytest.approx(6.25)

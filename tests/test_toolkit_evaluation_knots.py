"""The knot's position against the silhouette (toolkit.evaluation.knots)."""
import json

import numpy as np
import pytest

from monodbh.models.synthetic import generate_sample
from monodbh.models.synthetic import scene as scene_mod
from monodbh.toolkit.evaluation import knots


@pytest.fixture(scope="module")
def knotted():
    out = generate_sample(9000, 0, (96, 72))        # sample 0 of the benchmark's seed has a knot
    ring = next(r for r in out["scene"].trees[out["meta"]["roped_tree"] - 1].rings if r.is_rope)
    assert ring.knot
    return json.loads(json.dumps(out["meta"]))


def _with_knot_at(monkeypatch, meta, where):
    """Draw the scene again with the roped stem's knot at the stem's front ("front") or at the
    angle where its surface is farthest to one side as the camera sees it ("flank"), or none."""
    orig = scene_mod.sample_scene

    def patched(*a, **k):
        sc = orig(*a, **k)
        t = sc.trees[meta["roped_tree"] - 1]
        ring = next(r for r in t.rings if r.is_rope)
        C = np.asarray(meta["t_world_from_cam"], float)
        th = np.linspace(0, 2 * np.pi, 720, endpoint=False)
        V = t.surface_point(th, np.full(th.shape, ring.s_m)) - C
        w = t.axis_point(ring.s_m) - C
        w = w - (w @ t.axis) * t.axis
        u = np.cross(t.axis, w / np.linalg.norm(w))
        if where == "none":
            ring.knot = False
        else:
            ring.knot_theta = float(th[np.argmin(np.linalg.norm(V, axis=1))] if where == "front"
                                    else th[np.argmax(V @ u / np.linalg.norm(V, axis=1))])
        return sc
    monkeypatch.setattr(scene_mod, "sample_scene", patched)


def test_knot_on_the_flank_sticks_out_and_at_the_front_does_not(knotted, monkeypatch):
    _with_knot_at(monkeypatch, knotted, "flank")
    flank = knots.knot_out_fraction(knotted)
    _with_knot_at(monkeypatch, knotted, "front")
    front = knots.knot_out_fraction(knotted)
    _with_knot_at(monkeypatch, knotted, "none")
    none = knots.knot_out_fraction(knotted)
    # a knot at least 19 mm past a stem of at most 70 cm: over 2 % of its width
    assert flank > 0.02 and front == 0.0 and none == 0.0


def test_no_rope_or_another_scene_gives_none(knotted):
    assert knots.knot_out_fraction(dict(knotted, roped_tree=None)) is None
    other = json.loads(json.dumps(knotted))
    next(t for t in other["trees"] if t["id"] == other["roped_tree"])["dbh_m"] += 0.01
    assert knots.knot_out_fraction(other) is None

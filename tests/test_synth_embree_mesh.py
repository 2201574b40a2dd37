"""The zero-copy embree meshes give the same hits as embreex's own TriangleMesh."""
import numpy as np
import pytest

pytest.importorskip("embreex")

from embreex import rtcore_scene  # noqa: E402
from embreex.mesh_construction import TriangleMesh  # noqa: E402

from monodbh.models.synthetic.embree_mesh import add_triangles, fast_path_available  # noqa: E402


def _soup(seed=0, nv=3000, nf=2000, z=10.0):
    rng = np.random.default_rng(seed)
    V = (rng.normal(size=(nv, 3)) * 2 + [0, 0, z]).astype(np.float32)
    F = rng.integers(0, nv, (nf, 3)).astype(np.int32)
    return V, F


def test_fast_path_is_used_with_the_pinned_embreex():
    assert fast_path_available()


def test_shared_buffers_give_identical_hits_to_trianglemesh():
    V, F = _soup()
    V2, F2 = _soup(1, 500, 300, z=-10.0)
    rng = np.random.default_rng(5)
    o = np.zeros((4000, 3), np.float32)
    d = rng.normal(size=(4000, 3)).astype(np.float32)
    ref = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=ref, vertices=V, indices=F)
    TriangleMesh(scene=ref, vertices=V2, indices=F2)
    new = rtcore_scene.EmbreeScene()
    keep: list = []
    assert add_triangles(new, V, F, keep) == 0
    assert add_triangles(new, V2, F2, keep) == 1
    r1, r2 = ref.run(o, d, output=1), new.run(o, d, output=1)
    assert (r1["geomID"] >= 0).sum() > 200 and set(np.unique(r1["geomID"])) == {-1, 0, 1}
    for k in ("geomID", "primID", "tfar", "Ng"):
        np.testing.assert_array_equal(r1[k], r2[k])
    occ1 = ref.run(o, d, dists=10.0, query="OCCLUDED")
    occ2 = new.run(o, d, dists=10.0, query="OCCLUDED")
    np.testing.assert_array_equal(occ1, occ2)


def test_adding_to_a_queried_scene_is_refused():
    V, F = _soup()
    es = rtcore_scene.EmbreeScene()
    keep: list = []
    add_triangles(es, V, F, keep)
    es.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))
    with pytest.raises(ValueError):
        add_triangles(es, V, F, keep)

"""Triangle meshes for a :class:`~.scene.Scene`: stems, branches, crowns, rope, ground, clutter.

Every face carries an object index into :class:`MeshSet.objects`, a small table telling the
renderer what was hit (kind, tree id, semantic class, material).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .scene import Scene, Tree, ground_height
from .vec import cross3, norm_rows

__all__ = ["MeshSet", "build_meshes", "SEM_SKY", "SEM_GROUND", "SEM_VEG", "SEM_TREE", "SEM_OTHER"]

SEM_SKY, SEM_GROUND, SEM_VEG, SEM_TREE, SEM_OTHER = 0, 1, 2, 3, 4


@dataclass
class MeshSet:
    verts: list = field(default_factory=list)
    faces: list = field(default_factory=list)
    face_obj: list = field(default_factory=list)
    objects: list = field(default_factory=list)
    offsets: list = field(default_factory=list)
    _nv: int = 0

    def add(self, v: np.ndarray, f: np.ndarray, **obj) -> int:
        oid = len(self.objects)
        self.objects.append(obj)
        self.offsets.append(self._nv)
        self.verts.append(np.asarray(v, np.float64))
        self.faces.append(np.asarray(f, np.int64) + self._nv)
        self.face_obj.append(np.full(len(f), oid, np.int32))
        self._nv += len(v)
        return oid

    def arrays(self):
        """Concatenated ``(V, 3)`` vertices, ``(F, 3)`` faces and ``(F,)`` object ids."""
        return (np.concatenate(self.verts), np.concatenate(self.faces).astype(np.int32),
                np.concatenate(self.face_obj))


def _grid_faces(rows: int, cols: int, wrap: bool) -> np.ndarray:
    """Faces of a (rows x cols) vertex grid; ``wrap`` closes the columns into a tube."""
    c1 = cols if wrap else cols - 1
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(c1), indexing="ij")
    a = i * cols + j
    b = i * cols + (j + 1) % cols
    c = (i + 1) * cols + j
    d = (i + 1) * cols + (j + 1) % cols
    return np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])


def _tube(p: np.ndarray, radius: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Tube along polyline ``p`` (M, 3) with radii (M,) and ``n`` sides."""
    t = np.gradient(p, axis=0)
    t /= norm_rows(t, keepdims=True) + 1e-12
    ref = np.where(np.abs(t[:, 2:3]) < 0.9, [[0, 0, 1.0]], [[1.0, 0, 0]])
    e1 = cross3(ref, t)
    e1 /= norm_rows(e1, keepdims=True)
    e2 = cross3(t, e1)
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    v = (p[:, None] + radius[:, None, None] * (np.cos(th)[None, :, None] * e1[:, None]
                                               + np.sin(th)[None, :, None] * e2[:, None]))
    return v.reshape(-1, 3), _grid_faces(len(p), n, wrap=True)


def _stem_mesh(tree: Tree) -> tuple[np.ndarray, np.ndarray]:
    n = tree.segments()
    top = tree.height_m
    if tree.lod == 0 and tree.id == 1:
        s = np.unique(np.r_[np.linspace(-0.3, 0.0, 3), np.linspace(0.0, 3.0, 31), np.linspace(3.0, top, 16)])
    elif tree.lod == 0:
        s = np.unique(np.r_[np.linspace(-0.3, 0.0, 2), np.linspace(0.0, 3.0, 13), np.linspace(3.0, top, 10)])
    elif tree.lod == 1:
        s = np.unique(np.r_[-0.3, np.linspace(0.0, 3.0, 13), np.linspace(3.0, top, 10)])
    else:
        s = np.r_[-0.3, np.linspace(0.0, top, 8)]
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    S, TH = np.meshgrid(s, th, indexing="ij")
    v = tree.surface_point(TH.ravel(), S.ravel())
    f = _grid_faces(len(s), n, wrap=True)
    return v, f


def _ring_mesh(tree: Tree, ring, rng) -> list:
    """Rope (a tube hugging the stem) or flagging tape (a thin band), plus knot and tails."""
    out = []
    s = ring.s_m
    if ring.width_m <= 0:                       # round rope
        m = 160 if tree.lod == 0 else 48
        th = np.linspace(0, 2 * np.pi, m, endpoint=False)
        ss = s + rng.normal(0, 0.0015, 1)[0] * np.cos(th - rng.uniform(0, 6.3))
        centre = tree.surface_point(th, ss, offset=ring.tube_radius_m * 0.85)
        centre = np.concatenate([centre, centre[:1]])
        v, f = _tube(centre, np.full(len(centre), ring.tube_radius_m), 8)
        out.append((v, f))
    else:                                       # tape: band of width w
        m = 96
        th = np.linspace(0, 2 * np.pi, m + 1)
        ss = np.array([s - ring.width_m / 2, s + ring.width_m / 2])
        TH, SS = np.meshgrid(th, ss, indexing="ij")
        v = tree.surface_point(TH.ravel(), SS.ravel(), offset=0.002)
        f = _grid_faces(m + 1, 2, wrap=False)
        f = np.concatenate([f, f[:, ::-1]])
        out.append((v, f))
    if ring.knot:
        kp = tree.surface_point(np.array([ring.knot_theta]), np.array([s]), offset=2 * max(ring.tube_radius_m, 0.004))[0]
        out.append(_blob(kp, 2.2 * max(ring.tube_radius_m, 0.005)))
        radial = kp - tree.axis_point(s)
        radial /= np.linalg.norm(radial) + 1e-9
        for side in (-1, 1):
            L = ring.tail_len_m * rng.uniform(0.6, 1.0)
            tt = np.linspace(0, 1, 10)
            lateral = cross3(tree.axis, radial) * side * 0.02
            p = kp[None] + (-tree.axis[None] * L * tt[:, None] + radial[None] * 0.03 * np.sin(tt * 3)[:, None]
                            + lateral[None] * tt[:, None])
            if ring.width_m > 0:
                v, f = _tube(p, np.full(len(p), 0.006), 4)
            else:
                v, f = _tube(p, np.full(len(p), ring.tube_radius_m), 6)
            out.append((v, f))
    return out


def _blob(c, r):
    """Small icosahedron-like blob (knot)."""
    t = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], np.float64)
    v = v / norm_rows(v, keepdims=True) * r + c
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    return v, f


def _leaves(rng, centres: np.ndarray, radii: np.ndarray, per: int, size: float, flat_up: float = 0.0):
    """Random leaf triangles inside spheres (``centres`` (C, 3), ``radii`` (C,))."""
    C = len(centres)
    if C == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    n = C * per
    idx = np.repeat(np.arange(C), per)
    d = rng.normal(size=(n, 3))
    d /= norm_rows(d, keepdims=True)
    rad = radii[idx] * rng.random(n) ** 0.5          # denser towards the outside
    p = centres[idx] + d * rad[:, None]
    a = rng.normal(size=(n, 3))
    a[:, 2] *= (1 - flat_up)
    a /= norm_rows(a, keepdims=True)
    b = cross3(a, rng.normal(size=(n, 3)))
    b /= norm_rows(b, keepdims=True) + 1e-9
    sz = size * rng.uniform(0.6, 1.4, n)[:, None]
    v = np.stack([p - a * sz * 0.5, p + a * sz * 0.5, p + b * sz * 0.6], 1).reshape(-1, 3)
    f = np.arange(3 * n).reshape(n, 3)
    return v, f


def _crown(tree: Tree, rng):
    """Leaf clusters (broadleaf) or whorled cones (conifers) above the crown base."""
    if tree.dead:
        return None
    sp_conifer = tree.species in ("pine", "spruce")
    top = tree.height_m
    cb = tree.crown_base_m
    L = top - cb
    lod_per = int(round((55, 28, 12)[tree.lod] * tree.crown_density ** 0.5))
    size = (0.3, 0.55, 1.0)[tree.lod] * float(np.clip(tree.r_bh / 0.12, 0.3, 1.0)) * tree.leaf_scale
    if sp_conifer and tree.species == "spruce":
        nc = (40, 20, 8)[tree.lod]
        s = cb + L * rng.random(nc) ** 0.8
        frac = (top - s) / L
        rad = tree.crown_radius_m * frac
        ang = rng.uniform(0, 2 * np.pi, nc)
        off = rad * rng.uniform(0.2, 0.9, nc)
        c = (tree.base[None] + s[:, None] * tree.axis[None]
             + off[:, None] * (np.cos(ang)[:, None] * tree.e1[None] + np.sin(ang)[:, None] * tree.e2[None]))
        r = np.maximum(0.25, rad * 0.55)
    else:
        nc = int(round((36, 18, 8)[tree.lod] * tree.crown_density ** 0.5))
        u = rng.normal(size=(nc, 3))
        u /= norm_rows(u, keepdims=True)
        u *= rng.random(nc)[:, None] ** 0.4
        centre = tree.base + (cb + 0.55 * L) * tree.axis
        c = centre + np.stack([u[:, 0] * tree.crown_radius_m, u[:, 1] * tree.crown_radius_m, u[:, 2] * 0.5 * L], 1)
        r = rng.uniform(0.5, 1.0, nc) * max(0.4, tree.crown_radius_m * 0.5)
    return _leaves(rng, c, r, lod_per, size)


def _branch_tubes(tree: Tree):
    out = []
    for s, th, elev, length, rad in tree.branches:
        d = (np.cos(elev) * (np.cos(th) * tree.e1 + np.sin(th) * tree.e2) + np.sin(elev) * tree.axis)
        p0 = tree.axis_point(s)
        tt = np.linspace(0, 1, 6)
        droop = -0.15 * length * tt ** 2
        p = p0[None] + d[None] * length * tt[:, None] + np.array([0, 0, 1.0])[None] * droop[:, None]
        v, f = _tube(p, rad * (1 - 0.85 * tt), 6)
        out.append((v, f))
    return out


def _in_view(tree: Tree, cam, margin: float = 0.25) -> bool:
    """Whether any part of the tree (axis and crown extent) may appear in the picture, with a
    ``margin`` (fraction of the image size) around it."""
    s = np.linspace(0.0, tree.height_m, 7)
    axis = tree.base[None] + s[:, None] * tree.axis[None]
    r = max(tree.crown_radius_m, 4 * tree.r_bh, 0.5)
    offs = np.array([[0, 0, 0], [r, 0, 0], [-r, 0, 0], [0, r, 0], [0, -r, 0]], float)
    P = (axis[:, None] + offs[None]).reshape(-1, 3)
    pc = (P - cam.t_wc) @ cam.R_wc
    if np.min(norm_rows(pc)) < 2.0 + r:
        return True
    front = pc[:, 2] > 0.05
    if not front.any():
        return False
    uv = pc[front, :2] / pc[front, 2:3] * np.array([cam.K[0, 0], cam.K[1, 1]]) + cam.K[:2, 2]
    mx, my = margin * cam.width, margin * cam.height
    inside = ((uv[:, 0] > -mx) & (uv[:, 0] < cam.width + mx) & (uv[:, 1] > -my) & (uv[:, 1] < cam.height + my))
    if inside.any():
        return True
    # a tree spanning the view (points on both sides of it, or above and below)
    return bool((uv[:, 0].min() < 0 < uv[:, 0].max()) and (uv[:, 1].min() < cam.height and uv[:, 1].max() > 0))


def build_meshes(scene: Scene, rng: np.random.Generator) -> MeshSet:
    """Build every mesh of the scene.

    Object records have keys ``kind`` (``stem``, ``branch``, ``leaf``, ``rope``, ``tape``,
    ``ground``, ``bush``, ``grass``, ``log``, ``jacket``, ``skin``, ``trousers``),
    ``tree`` (tree id or 0), ``semantic`` and ``instance``.
    """
    ms = MeshSet()
    cam = scene.camera
    # ---- ground height field: fine near the camera, coarse far away
    cx, cy = cam.t_wc[0], cam.t_wc[1]
    ext = 70.0
    g = np.sign(np.linspace(-1, 1, 121)) * np.linspace(-1, 1, 121) ** 2 * ext
    gx, gy = np.meshgrid(cx + g, cy + g)
    gz = ground_height(scene.ground, gx, gy)
    ms.add(np.stack([gx.ravel(), gy.ravel(), gz.ravel()], 1), _grid_faces(121, 121, wrap=False),
           kind="ground", tree=0, semantic=SEM_GROUND, instance=0)
    for t in scene.trees:
        inst = t.id
        if t.lod < 2 and t.id != 1 and not _in_view(t, cam):
            # out of the picture: only its shadow and sky occlusion matter, a coarse proxy will do
            t.lod = 2
        v, f = _stem_mesh(t)
        ms.add(v, f, kind="stem", tree=t.id, semantic=SEM_TREE, instance=inst)
        for v, f in (_branch_tubes(t) if t.lod < 2 else ()):
            ms.add(v, f, kind="branch", tree=t.id, semantic=SEM_TREE, instance=inst)
        cr = _crown(t, rng)
        if cr is not None and len(cr[0]):
            ms.add(cr[0], cr[1], kind="leaf", tree=t.id, semantic=SEM_TREE, instance=inst, rgb=t.leaf_rgb)
        for ring in t.rings:
            for v, f in _ring_mesh(t, ring, rng):
                ms.add(v, f, kind="rope" if ring.is_rope else "tape", tree=t.id, semantic=SEM_TREE,
                       instance=inst, rgb=ring.rgb)
    for c, r, rgb, red in scene.bushes:
        nc = int(rng.integers(3, 7))
        cc = c[None] + rng.normal(0, r * 0.4, (nc, 3)) * [1, 1, 0.5]
        v, f = _leaves(rng, cc, np.full(nc, r * 0.7), 90, 0.08)
        ms.add(v, f, kind="bush", tree=0, semantic=SEM_VEG, instance=0, rgb=rgb)
    for c, r, dens, h in scene.grass:
        n = int(min(dens * np.pi * r * r, 2500))
        if n <= 0:
            continue
        rr = r * np.sqrt(rng.random(n))
        aa = rng.uniform(0, 2 * np.pi, n)
        x = c[0] + rr * np.cos(aa)
        y = c[1] + rr * np.sin(aa)
        z = ground_height(scene.ground, x, y)
        base = np.stack([x, y, z], 1)
        w = rng.uniform(0.006, 0.015, n)
        ang = rng.uniform(0, np.pi, n)
        side = np.stack([np.cos(ang), np.sin(ang), np.zeros(n)], 1) * w[:, None]
        tip = base + np.stack([rng.normal(0, 0.05, n), rng.normal(0, 0.05, n), h * rng.uniform(0.5, 1.2, n)], 1)
        v = np.stack([base - side, base + side, tip], 1).reshape(-1, 3)
        ms.add(v, np.arange(3 * n).reshape(n, 3), kind="grass", tree=0, semantic=SEM_VEG, instance=0,
               rgb=(rng.uniform(0.06, 0.14), rng.uniform(0.14, 0.24), rng.uniform(0.03, 0.06)))
    for p0, p1, r in scene.logs:
        tt = np.linspace(0, 1, 6)[:, None]
        v, f = _tube(p0[None] * (1 - tt) + p1[None] * tt, np.full(6, r), 10)
        ms.add(v, f, kind="log", tree=0, semantic=SEM_VEG, instance=0)
    if scene.person is not None:
        pc, hgt = scene.person["center"], scene.person["height"]
        up = np.array([0, 0, 1.0])
        for part, z0, z1, rad, kind in (("legs", 0.0, 0.48, 0.14, "trousers"), ("torso", 0.48, 0.82, 0.2, "jacket"),
                                        ("head", 0.84, 1.0, 0.1, "skin")):
            tt = np.linspace(z0, z1, 5)[:, None] * hgt
            v, f = _tube(pc[None] + up[None] * tt, np.full(5, rad), 12)
            ms.add(v, f, kind=kind, tree=0, semantic=SEM_OTHER, instance=0,
                   rgb=scene.person["jacket"] if kind == "jacket" else ((0.5, 0.35, 0.28) if kind == "skin" else (0.05, 0.05, 0.07)))
    return ms

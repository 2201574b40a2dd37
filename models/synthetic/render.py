"""Ray-cast renderer (embreex) for synthetic forest scenes, with exact ground truth.

Pipeline per sample: rays through the distorted pixel grid -> closest hits -> materials,
procedural textures, sun + sky + bounce lighting with cast shadows and a canopy-openness term
-> adaptive supersampling of object edges and of the rope band -> aerial haze -> a phone-like
camera (exposure, white balance, noise, blur, JPEG); the other looks (:mod:`.looks`) change
the textures' colours or sources, the light and the camera. Ground truth (depth, labels, rope mask,
per-tree nearest/farthest surface depth z1/z2) comes from the same rays.
"""
from __future__ import annotations

import time
from dataclasses import replace

import cv2
import numpy as np
from embreex import rtcore, rtcore_scene

from .embree_mesh import add_triangles
from .geometry import SEM_SKY, SEM_TREE, MeshSet, build_meshes
from .looks import (HELDOUT, LOOKS, RANDOMIZED, HeldoutShading, PhotoTextures, RandomizedShading, heldout_light,
                    heldout_post, look_rng, photo_textures, randomized_light, randomized_post)
from .noise import fbm_texture, ridged, sample_texture
from .scene import BREAST_HEIGHT_M, SPECIES, Scene, ground_height
from .vec import cross3, norm_rows

__all__ = ["render_scene", "pixel_rays", "Tracer"]

_F32 = np.float32


class Tracer:
    """Closest-hit and occlusion queries on a set of triangles (embree BVH).

    Parameters
    ----------
    verts : (V, 3) float64 world vertices.
    faces : (F, 3) int32.
    origin : (3,) world point subtracted before converting to float32 (precision).
    """

    def __init__(self, verts: np.ndarray, faces: np.ndarray, origin: np.ndarray):
        self.origin = np.asarray(origin, np.float64)
        self.scene = rtcore_scene.EmbreeScene()
        self._keep: list = []     # buffers embree shares (see embree_mesh)
        add_triangles(self.scene, (verts - self.origin).astype(_F32), faces, self._keep)

    def first(self, o: np.ndarray, d: np.ndarray) -> dict:
        """Closest hits: dict with ``prim`` (N,) (-1 = miss), ``t`` (N,), ``Ng`` (N, 3)."""
        if len(o) == 0:
            return dict(prim=np.zeros(0, np.int64), t=np.zeros(0), Ng=np.zeros((0, 3)))
        r = self.scene.run((o - self.origin).astype(_F32), d.astype(_F32), output=1)
        prim = np.where(r["geomID"] >= 0, r["primID"], -1).astype(np.int64)
        return dict(prim=prim, t=r["tfar"].astype(np.float64), Ng=r["Ng"].astype(np.float64))

    def occluded(self, o: np.ndarray, d: np.ndarray, tmax: float | np.ndarray = 1e9) -> np.ndarray:
        """(N,) bool: whether anything lies on the segment ``o + t d, 0 < t < tmax``."""
        if len(o) == 0:
            return np.zeros(0, bool)
        dists = np.broadcast_to(np.asarray(tmax, _F32), (len(o),)).astype(_F32)
        r = self.scene.run((o - self.origin).astype(_F32), d.astype(_F32), dists=dists, query="OCCLUDED")
        return np.asarray(r) != -1


def pixel_rays(cam, px: np.ndarray) -> np.ndarray:
    """Unit ray directions in the camera frame through distorted pixel positions.

    Parameters
    ----------
    cam : :class:`~.scene.Camera`
    px : (N, 2) float pixel coordinates (OpenCV convention: pixel centres at integers).

    Returns
    -------
    (N, 3) float64 unit vectors.
    """
    if np.any(cam.dist):
        und = cv2.undistortPoints(px.reshape(-1, 1, 2).astype(np.float64), cam.K, cam.dist, None, None, None,
                                      (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)).reshape(-1, 2)
    else:
        und = np.stack([(px[:, 0] - cam.K[0, 2]) / cam.K[0, 0], (px[:, 1] - cam.K[1, 2]) / cam.K[1, 1]], 1)
    d = np.concatenate([und, np.ones((len(und), 1))], 1)
    return d / norm_rows(d, keepdims=True)


def grid_rays(cam, step: int = 4) -> np.ndarray:
    """Unit camera-frame rays ``(H*W, 3)`` through every pixel centre.

    Distortion is smooth, so the iterative undistortion runs on a grid every ``step`` pixels
    (plus the last row/column) and is interpolated bilinearly in between (error < 1e-4 px).
    """
    W, H = cam.width, cam.height
    if not np.any(cam.dist):
        v, u = np.mgrid[0:H, 0:W]
        return pixel_rays(cam, np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
    xs = np.unique(np.r_[np.arange(0, W, step), W - 1]).astype(np.float64)
    ys = np.unique(np.r_[np.arange(0, H, step), H - 1]).astype(np.float64)
    gx, gy = np.meshgrid(xs, ys)
    r = pixel_rays(cam, np.stack([gx.ravel(), gy.ravel()], 1))
    r = (r[:, :2] / r[:, 2:3]).reshape(len(ys), len(xs), 2)
    fx = np.interp(np.arange(W), xs, np.arange(len(xs)))
    fy = np.interp(np.arange(H), ys, np.arange(len(ys)))
    mx, my = np.meshgrid(fx.astype(np.float32), fy.astype(np.float32))
    und = np.stack([cv2.remap(r[..., c].astype(np.float32), mx, my, cv2.INTER_LINEAR) for c in (0, 1)], -1)
    und = und.reshape(-1, 2).astype(np.float64)
    d = np.concatenate([und, np.ones((len(und), 1))], 1)
    return d / norm_rows(d, keepdims=True)


def _textures(rng):
    return dict(
        fine=fbm_texture(rng, 256, 5, 8),
        mid=fbm_texture(rng, 256, 4, 4),
        coarse=fbm_texture(rng, 128, 3, 2),
        ridge=ridged(fbm_texture(rng, 256, 4, 8)),
        ridge2=ridged(fbm_texture(rng, 256, 3, 4)),
    )


def _sky(light, dirs: np.ndarray, tex) -> np.ndarray:
    """Sky radiance for world directions ``(N, 3)`` -> ``(N, 3)``."""
    el = np.clip(dirs[:, 2], -0.2, 1.0)
    zen = np.array([0.25, 0.42, 0.8]) * (1 - light.overcast) + np.array([0.75, 0.77, 0.8]) * light.overcast
    hor = light.haze_rgb * 1.2
    t = np.clip(el, 0, 1)[:, None] ** 0.5
    col = hor * (1 - t) + zen * t
    az = np.arctan2(dirs[:, 1], dirs[:, 0])
    cl = sample_texture(tex["mid"], az / (2 * np.pi) * 4, np.clip(el, 0, 1) * 1.5)
    cloud = np.clip((cl - 0.5 + 0.3 * light.overcast) * 2.5, 0, 1)[:, None]
    col = col * (1 - cloud * 0.7) + np.array([0.9, 0.9, 0.92]) * cloud * 0.7
    cs = dirs @ light.sun_dir
    glow = (np.clip(cs, 0, 1) ** 64 * 3 + (cs > 0.9995) * 30) * (1 - light.overcast)
    return (col * 1.6 + glow[:, None] * np.array([1.0, 0.95, 0.85])) * 1.0


class _Shader:
    def __init__(self, scene: Scene, ms: MeshSet, tracer: Tracer, face_obj: np.ndarray, rng):
        self.scene, self.ms, self.tracer, self.face_obj = scene, ms, tracer, face_obj
        self.tex = _textures(rng)
        self.obj_kind = np.array([o["kind"] for o in ms.objects])
        self.obj_rgb = np.array([o.get("rgb", (0.5, 0.5, 0.5)) for o in ms.objects], np.float64)
        self.obj_is_rope = np.array([o["kind"] == "rope" for o in ms.objects])
        self.obj_is_stem = np.array([o["kind"] in ("stem", "rope", "tape") for o in ms.objects])
        self.obj_sem = np.array([o["semantic"] for o in ms.objects], np.uint8)
        self.obj_inst = np.array([o["instance"] for o in ms.objects], np.uint16)
        self.obj_tree = np.array([o["tree"] for o in ms.objects], np.int64)
        self.trees = {t.id: t for t in scene.trees}
        self.lichen = {t.id: (rng.random() < 0.4) for t in scene.trees}

    # -------------------------------------------------------------------- hits
    def trace(self, o, d):
        h = self.tracer.first(o, d)
        hit = h["prim"] >= 0
        obj = np.full(len(o), -1, np.int64)
        obj[hit] = self.face_obj[h["prim"][hit]]
        h["obj"] = obj
        h["hit"] = hit
        return h

    def shade(self, o: np.ndarray, d: np.ndarray, h: dict, ao: np.ndarray | None = None) -> np.ndarray:
        """Linear radiance ``(N, 3)`` for rays ``o + t d`` with hit record ``h``."""
        sc, L = self.scene, self.scene.light
        n = len(o)
        col = np.zeros((n, 3))
        hit = h["hit"]
        col[~hit] = self._sky(L, d[~hit])
        if not hit.any():
            return col
        idx = np.nonzero(hit)[0]
        p = o[idx] + d[idx] * h["t"][idx, None]
        dd = d[idx]
        obj = h["obj"][idx]
        kind = self.obj_kind[obj]
        nrm = h["Ng"][idx].copy()
        nrm /= norm_rows(nrm, keepdims=True) + 1e-12
        alb = np.zeros((len(idx), 3))
        trans = np.zeros(len(idx))                     # leaf translucency

        # ground
        m = kind == "ground"
        if m.any():
            q = p[m]
            eps = 0.05
            gz = ground_height(sc.ground, q[:, 0], q[:, 1])
            gx = (ground_height(sc.ground, q[:, 0] + eps, q[:, 1]) - gz) / eps
            gy = (ground_height(sc.ground, q[:, 0], q[:, 1] + eps) - gz) / eps
            nn = np.stack([-gx, -gy, np.ones_like(gx)], 1)
            nrm[m] = nn / norm_rows(nn, keepdims=True)
            alb[m] = self._ground_albedo(q)

        # stems: analytic normal, bark textures by species, paint marks
        m = kind == "stem"
        if m.any():
            ii = np.nonzero(m)[0]
            tid = self.obj_tree[obj[ii]]
            for t_id in np.unique(tid):
                t = self.trees[int(t_id)]
                jj = ii[tid == t_id]
                rel = p[jj] - t.base
                s = rel @ t.axis
                rad = rel - s[:, None] * t.axis
                th = np.arctan2(rad @ t.e2, rad @ t.e1)
                nr = rad / (norm_rows(rad, keepdims=True) + 1e-12)
                alb[jj], bump = self._bark(t, th, s)
                tang = cross3(t.axis, nr)
                nrm[jj] = nr + bump[:, 0:1] * tang + bump[:, 1:2] * t.axis
                nrm[jj] /= norm_rows(nrm[jj], keepdims=True)
        # branches, logs
        m = np.isin(kind, ("branch", "log"))
        if m.any():
            c = sample_texture(self.tex["fine"], p[m, 0] * 3 + p[m, 2], p[m, 1] * 3 + p[m, 2] * 2)
            alb[m] = np.array([0.16, 0.13, 0.10]) * (0.6 + 0.8 * c[:, None])
        # foliage, bushes, grass
        m = np.isin(kind, ("leaf", "bush", "grass"))
        if m.any():
            ii = np.nonzero(m)[0]
            alb[ii] = self._foliage_albedo(self.obj_rgb[obj[ii]], h["prim"][idx[ii]], p[ii])
            trans[ii] = 0.35
        # rope / tape / person: flat colours with fibre noise
        m = np.isin(kind, ("rope", "tape", "jacket", "skin", "trousers"))
        if m.any():
            ii = np.nonzero(m)[0]
            base = self.obj_rgb[obj[ii]]
            c = sample_texture(self.tex["fine"], p[ii, 0] * 40 + p[ii, 2] * 40, p[ii, 1] * 40)
            alb[ii] = base * (0.8 + 0.4 * c[:, None])

        # two-sided: normals face the viewer
        flip = np.sum(nrm * dd, 1) > 0
        nrm[flip] *= -1
        ndl = nrm @ L.sun_dir
        lit = np.clip(ndl, 0, None)
        back = (ndl < 0) & (trans > 0)
        cand = (lit > 0) | back
        shadow = np.ones(len(idx))
        if L.overcast < 0.95 and cand.any():
            ci = np.nonzero(cand)[0]
            occ = self.tracer.occluded(p[ci] + nrm[ci] * 1e-3 * np.where(back[ci], -1, 1)[:, None],
                                       np.broadcast_to(L.sun_dir, (len(ci), 3)).copy())
            shadow[ci] = np.where(occ, 0.0, 1.0)
        direct = (lit + trans * np.clip(-ndl, 0, None) * 0.6) * shadow
        sky_amb = (0.55 + 0.45 * nrm[:, 2:3]) * L.sky_rgb[None]
        if ao is not None:
            sky_amb = sky_amb * ao[idx][:, None]
        amb = sky_amb + (0.5 - 0.5 * nrm[:, 2:3]) * L.ground_rgb[None]
        rad = alb * (amb + direct[:, None] * L.sun_rgb[None])
        # aerial perspective
        fog = np.exp(-h["t"][idx] / L.fog_m)[:, None]
        col[idx] = rad * fog + L.haze_rgb[None] * (1 - fog)
        return col

    def _sky(self, light, dirs: np.ndarray) -> np.ndarray:
        """Sky radiance (N, 3) for world directions (N, 3)."""
        return _sky(light, dirs, self.tex)

    def _ground_albedo(self, q: np.ndarray) -> np.ndarray:
        """Ground albedo (N, 3) at world points ``q`` (N, 3)."""
        c1 = sample_texture(self.tex["coarse"], q[:, 0] / 23.0, q[:, 1] / 23.0)
        c2 = sample_texture(self.tex["mid"], q[:, 0] / 3.1, q[:, 1] / 3.1)
        c3 = sample_texture(self.tex["fine"], q[:, 0] / 0.7, q[:, 1] / 0.7)
        litter = np.array([0.22, 0.13, 0.06]) * (0.6 + 0.8 * c3[:, None])
        moss = np.array([0.08, 0.15, 0.04]) * (0.7 + 0.6 * c3[:, None])
        soil = np.array([0.09, 0.07, 0.05]) * (0.7 + 0.6 * c2[:, None])
        w_moss = np.clip((c1 - 0.55) * 5, 0, 1)[:, None]
        w_soil = np.clip((c2 - 0.7) * 5, 0, 1)[:, None]
        alb = litter * (1 - w_moss) + moss * w_moss
        alb = alb * (1 - w_soil) + soil * w_soil
        lawn = float(self.scene.ground.get("lawn", 0.0))
        if lawn > 0:                                     # park scenes: mown grass, a few bare patches
            grass = np.array([0.07, 0.16, 0.03]) * (0.75 + 0.5 * c3[:, None]) * (0.8 + 0.4 * c1[:, None])
            w = lawn * np.clip(1.0 - (c2 - 0.72) * 6, 0, 1)[:, None]
            alb = alb * (1 - w) + grass * w
        return alb

    def _foliage_albedo(self, base: np.ndarray, prim: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Albedo (N, 3) of leaf, bush and grass hits: the objects' colours ``base`` (N, 3) varied
        per triangle (``prim`` (N,)); ``p`` (N, 3) are the world points."""
        var = ((prim * 2654435761) % 1000) / 1000.0
        return base * (0.6 + 0.8 * var[:, None])

    def _bark(self, t, th, s):
        """Bark albedo (N, 3) and a normal perturbation (N, 2) for stem points."""
        sp = SPECIES[t.species]
        circ = th * t.r_bh
        tex = self.tex
        base = np.array(sp["bark"]) * np.array(t.bark_tint)
        off = (t.seed % 997) / 997.0
        fine = sample_texture(tex["fine"], circ / 0.35 + off, s / 0.9 + off)
        if t.species == "birch":
            marks = sample_texture(tex["fine"], circ / 0.25 + off, s / 0.05)
            dark = np.clip((0.35 - marks) * 6, 0, 1) + np.clip((0.45 - s) * 2, 0, 1) * (fine < 0.55)
            dark = np.clip(dark, 0, 1)
            alb = base * (0.9 + 0.2 * fine[:, None]) * (1 - dark[:, None]) + np.array([0.04, 0.035, 0.03]) * dark[:, None]
            bump = np.zeros((len(th), 2))
        elif sp["furrow"] > 0.3:
            r1 = sample_texture(tex["ridge"], circ / (0.12 + 0.2 * t.r_bh) + off, s / 0.8 + off)
            r2 = sample_texture(tex["ridge"], (circ + 0.002) / (0.12 + 0.2 * t.r_bh) + off, s / 0.8 + off)
            depth = r1 ** 2
            cav = 1 - sp["furrow"] * (1 - depth) * 0.8
            alb = base * cav[:, None] * (0.85 + 0.3 * fine[:, None])
            if t.species == "pine":  # orange plates high on pine stems
                plates = np.clip((s - 3.0) / 4.0, 0, 1) * (r1 > 0.6)
                alb = alb * (1 - plates[:, None]) + np.array([0.45, 0.22, 0.1]) * plates[:, None]
            bump = np.stack([(r2 - r1) * 40, np.zeros_like(r1)], 1) * sp["furrow"]
            bump = np.clip(bump, -0.8, 0.8)
        else:
            mid = sample_texture(tex["mid"], circ / 0.6 + off, s / 1.5 + off)
            alb = base * (1 - sp["bark_var"] + 2 * sp["bark_var"] * (0.4 * fine + 0.6 * mid))[:, None]
            if t.species == "spruce":
                flakes = sample_texture(tex["fine"], circ / 0.08, s / 0.1)
                alb = alb * (0.75 + 0.5 * flakes[:, None])
            bump = np.zeros((len(th), 2))
        if self.lichen[t.id]:
            lc = sample_texture(tex["coarse"], circ / 0.5 + off, s / 0.7)
            w = np.clip((lc - 0.62) * 6, 0, 1)[:, None]
            alb = alb * (1 - w) + np.array([0.32, 0.36, 0.26]) * w
        moss = np.clip((0.5 - s) * 2.5, 0, 1) * np.clip(np.cos(th - off * 6.28), 0, 1) * (off > 0.5)
        alb = alb * (1 - moss[:, None]) + np.array([0.07, 0.14, 0.03]) * moss[:, None]
        if t.paint is not None:
            pt = t.paint
            dth = np.angle(np.exp(1j * (th - pt["theta0"])))
            pm = (np.abs(dth) < pt["dtheta"] / 2) & (s > pt["s0"]) & (s < pt["s1"])
            alb[pm] = np.array(pt["rgb"]) * (0.8 + 0.3 * fine[pm, None])
        return np.clip(alb, 0, 1), bump


def _camera_post(rng, lin: np.ndarray, light) -> np.ndarray:
    """Linear HDR image (H, W, 3) -> 8-bit sRGB like a phone pipeline (before JPEG)."""
    H, W = lin.shape[:2]
    lum = lin @ np.array([0.2126, 0.7152, 0.0722])
    key = np.exp(np.mean(np.log(lum + 1e-4)))
    x = lin * (0.22 / key) * light.exposure * light.wb[None, None]
    yy, xx = np.mgrid[0:H, 0:W]
    r2 = ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
    x = x * (1 - rng.uniform(0.1, 0.35) * r2)[..., None]
    x = 1 - np.exp(-x * 1.4)                                      # soft highlight roll-off
    sigma_read = rng.uniform(0.002, 0.012)
    x = x + rng.normal(0, 1, x.shape) * np.sqrt(sigma_read ** 2 + x.clip(0) * rng.uniform(0.0005, 0.004))
    x = np.clip(x, 0, 1) ** (1 / 2.2)
    img = (x * 255 + 0.5).astype(np.uint8)
    s = rng.uniform(0.0, 1.0)
    if s > 0.15:
        img = cv2.GaussianBlur(img, (0, 0), s * 0.9)
    return img


class _HeldoutShader(HeldoutShading, _Shader):
    """The shader with the held-out look's appearance (:mod:`.looks`)."""


class _RandomizedShader(RandomizedShading, _Shader):
    """The default shader with its colours and texture contrast randomised (:mod:`.looks`)."""


def _focus_m(scene: Scene) -> float:
    """Where the held-out look's lens is focused: the roped stem at 1.3 m, else 8 m (metres, z)."""
    cam = scene.camera
    if scene.roped_tree:
        t = scene.trees[scene.roped_tree - 1]
        return float(max(1.0, (cam.R_wc.T @ (t.axis_point(BREAST_HEIGHT_M) - cam.t_wc))[2]))
    return 8.0


def render_scene(scene: Scene, rng: np.random.Generator, *, aa: bool = True, shadows: bool = True,
                 jpeg_quality: int | None = None, look: str = "default",
                 textures: PhotoTextures | None = None) -> dict:
    """Render ``scene`` and its ground truth.

    ``look``: ``"default"``, ``"randomized"`` or ``"heldout"`` (:mod:`.looks`: the same geometry,
    labels and ground truth with another appearance; ``textures``: the held-out look's photo
    patches, default :func:`.looks.photo_textures`).

    Returns
    -------
    dict with ``rgb`` (H, W, 3) uint8 (JPEG-decoded), ``jpeg`` bytes, ``depth``, ``semantic``,
    ``instance``, ``rope``, ``stem`` (trunk pixels: stems and the rope or tape on them, not
    branches or foliage), ``z1``, ``z2`` (all (H, W)), ``stats``.
    """
    if look not in LOOKS:
        raise ValueError(f"unknown look {look!r} (expected one of {', '.join(LOOKS)})")
    cam = scene.camera
    W, H = cam.width, cam.height
    tm: dict[str, float] = {}
    t_last = [time.perf_counter()]

    def lap(name):
        t = time.perf_counter()
        tm[name] = tm.get(name, 0.0) + 1000 * (t - t_last[0])
        t_last[0] = t
    ms = build_meshes(scene, rng)
    V, F, face_obj = ms.arrays()
    lap("meshes")
    tracer = Tracer(V, F, cam.t_wc)
    if look in (HELDOUT, RANDOMIZED):
        # its own random stream: the scene's labels and geometry stay those of the default look
        lrng = look_rng(scene.seed, look)
        if look == HELDOUT:
            sh = _HeldoutShader(replace(scene, light=heldout_light(scene.light, lrng)), ms, tracer, face_obj, rng)
            sh._heldout_init(textures or photo_textures(), lrng)
        else:
            sh = _RandomizedShader(replace(scene, light=randomized_light(scene.light, lrng)), ms, tracer, face_obj, rng)
            sh._randomized_init(lrng)
    else:
        sh = _Shader(scene, ms, tracer, face_obj, rng)
    lap("bvh")

    v, u = np.mgrid[0:H, 0:W]
    px = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    dc = grid_rays(cam)
    d = dc @ cam.R_wc.T
    o = np.broadcast_to(cam.t_wc, d.shape).copy()
    h = sh.trace(o, d)
    lap("primary")

    # canopy openness (one cosine-weighted sky ray per hit, then smoothed in image space)
    # (every other pixel in each direction, then smoothed and upsampled)
    ao = np.ones(len(o))
    hit = h["hit"]
    sub = np.zeros((H, W), bool)
    sub[::2, ::2] = True
    sub = sub.ravel() & hit
    if sub.any():
        p = o[sub] + d[sub] * h["t"][sub, None]
        r1, r2 = rng.random(sub.sum()), rng.random(sub.sum())
        phi = 2 * np.pi * r1
        sq = np.sqrt(r2)
        dirs = np.stack([np.cos(phi) * sq, np.sin(phi) * sq, np.sqrt(1 - r2)], 1)
        occ = tracer.occluded(p + np.array([0, 0, 0.01]), dirs, 25.0)
        aomap = np.ones(len(o), np.float32)
        aomap[sub] = np.where(occ, 0.25, 1.0)
        small = aomap.reshape(H, W)[::2, ::2]
        small = cv2.blur(small, (5, 5))
        ao = cv2.resize(small, (W, H), interpolation=cv2.INTER_LINEAR).ravel().astype(np.float64)
    lap("ao")
    col = sh.shade(o, d, h, ao)
    lap("shade")

    obj = h["obj"]
    sem = np.where(obj >= 0, sh.obj_sem[np.maximum(obj, 0)], SEM_SKY).astype(np.uint8)
    inst = np.where(obj >= 0, sh.obj_inst[np.maximum(obj, 0)], 0).astype(np.uint16)
    is_rope = (obj >= 0) & sh.obj_is_rope[np.maximum(obj, 0)]
    rope_cov = is_rope.astype(np.float64)
    depth = np.where(hit, h["t"] * dc[:, 2], 0.0)

    # ---- adaptive supersampling: object edges and the rope band
    n_aa = 0
    if aa:
        oid = obj.reshape(H, W).astype(np.int32)
        e = np.zeros((H, W), bool)
        e[:, 1:] |= oid[:, 1:] != oid[:, :-1]
        e[:, :-1] |= oid[:, 1:] != oid[:, :-1]
        e[1:] |= oid[1:] != oid[:-1]
        e[:-1] |= oid[1:] != oid[:-1]
        band = np.zeros((H, W), bool)
        rope_objs = [k for k, ob in enumerate(ms.objects) if ob["kind"] in ("rope", "tape")]
        if rope_objs:
            rv = np.concatenate([ms.verts[k] for k in rope_objs])
            pc = (rv - cam.t_wc) @ cam.R_wc
            pc = pc[pc[:, 2] > 0.1]
            if len(pc):
                ip, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), cam.K, cam.dist)
                ip = np.round(ip.reshape(-1, 2)).astype(int)
                ok = (ip[:, 0] >= 0) & (ip[:, 0] < W) & (ip[:, 1] >= 0) & (ip[:, 1] < H)
                b8 = np.zeros((H, W), np.uint8)
                b8[ip[ok, 1], ip[ok, 0]] = 1
                band = cv2.dilate(b8, np.ones((5, 5), np.uint8)) > 0
                e |= band
        band_all = band.ravel()
        n_aa = int(e.sum())
        # edges of stems and branches (the outlines the DBH is measured from), at the pixel or a
        # 4-neighbour
        kind_stem = np.array([ob["kind"] in ("stem", "branch", "log") for ob in ms.objects] + [False])
        st = kind_stem[np.where(oid >= 0, oid, len(ms.objects))]
        st_n = st.copy()
        st_n[:, 1:] |= st[:, :-1]
        st_n[:, :-1] |= st[:, 1:]
        st_n[1:] |= st[:-1]
        st_n[:-1] |= st[1:]
        stem_e = st_n.ravel()
        # 4 sub-samples in the rope band (its coverage decides the rope label), 2 on stem and
        # branch outlines, 1 on the other edges (foliage, grass: a third of all pixels)
        groups = ((np.nonzero(e.ravel() & band_all)[0],
                   np.array([[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]])),
                  (np.nonzero(e.ravel() & ~band_all & stem_e)[0], np.array([[-0.25, -0.25], [0.25, 0.25]])),
                  (np.nonzero(e.ravel() & ~band_all & ~stem_e)[0], np.array([[0.25, -0.25]])))
        for ei, jit in groups:
            k = len(jit)
            if not len(ei):
                continue
            jit = jit + rng.uniform(-0.12, 0.12, (k, 2))
            sp = (px[ei][:, None] + jit[None]).reshape(-1, 2)
            dcs = pixel_rays(cam, sp)
            ds = dcs @ cam.R_wc.T
            os_ = np.broadcast_to(cam.t_wc, ds.shape).copy()
            hs = sh.trace(os_, ds)
            cs = sh.shade(os_, ds, hs, np.repeat(ao[ei], k))
            col[ei] = (col[ei] + cs.reshape(-1, k, 3).sum(1)) / (k + 1)
            ks = ((hs["obj"] >= 0) & sh.obj_is_rope[np.maximum(hs["obj"], 0)]).reshape(-1, k)
            rope_cov[ei] = (rope_cov[ei] + ks.sum(1)) / (k + 1)
            # a sub-pixel rope is labelled where it covers enough of the pixel
            inst_s = np.where(hs["obj"] >= 0, sh.obj_inst[np.maximum(hs["obj"], 0)], 0).reshape(-1, k)
            rp = (rope_cov[ei] >= 0.2) & ~is_rope[ei]
            if rp.any():
                sel = ei[rp]
                # take label/depth from the first rope sub-sample
                first = np.argmax(ks[rp], axis=1)
                rows = np.nonzero(rp)[0]
                inst[sel] = inst_s[rows, first]
                sem[sel] = SEM_TREE
                tt = hs["t"].reshape(-1, k)[rows, first]
                depth[sel] = tt * dcs.reshape(-1, k, 3)[rows, first, 2]
    lap("aa")
    rope = rope_cov >= 0.2
    # the trunks (a tree's stem, with the rope and tape on it), without branches and foliage
    stem = ((obj >= 0) & sh.obj_is_stem[np.maximum(obj, 0)]) | rope

    # ---- z1 / z2 for tree pixels: nearest = visible hit; farthest = reversed ray, same tree only
    z1 = np.zeros(H * W)
    z2 = np.zeros(H * W)
    tree_pix = inst > 0
    z1[tree_pix] = depth[tree_pix]
    t_vis = np.where(tree_pix, depth / np.maximum(dc[:, 2], 1e-9), 0.0)
    # one small BVH per visible tree: a reversed ray from beyond the tree meets only that tree,
    # and its first hit is the tree's farthest surface along the pixel's ray
    vis_ids = sorted(set(np.unique(inst[tree_pix]).tolist()) - {0})
    if vis_ids:
        by_tree: dict = {}
        for k, ob in enumerate(ms.objects):
            if ob["tree"]:
                by_tree.setdefault(ob["tree"], []).append(k)
        device = rtcore.EmbreeDevice()
        pix = np.nonzero(tree_pix)[0]
        order = np.argsort(inst[pix], kind="stable")
        pix = pix[order]
        bounds = np.searchsorted(inst[pix], np.r_[vis_ids, vis_ids[-1] + 1])
        for j, tid in enumerate(vis_ids):
            pj = pix[bounds[j]:bounds[j + 1]]
            objs = by_tree.get(tid, [])
            if not len(pj) or not objs:
                continue
            tv = np.concatenate([ms.verts[k] for k in objs])
            local = np.cumsum([0] + [len(ms.verts[k]) for k in objs[:-1]])
            tf = np.concatenate([ms.faces[k] - ms.offsets[k] + lo for k, lo in zip(objs, local)])
            tscene = rtcore_scene.EmbreeScene(device)
            tkeep: list = []
            add_triangles(tscene, (tv - cam.t_wc).astype(_F32), tf, tkeep)
            ext = float(norm_rows(tv - tv.mean(0)).max() * 2 + 1.0)
            dd = d[pj]
            tv_ = t_vis[pj]
            far = tv_ + ext
            r = tscene.run((dd * far[:, None]).astype(_F32), (-dd).astype(_F32), output=1)
            own = r["geomID"] >= 0
            tb = tv_.copy()
            tb[own] = np.maximum(far[own] - r["tfar"][own], tv_[own])
            z2[pj] = tb * dc[pj, 2]

    lap("z2")
    lin = col.reshape(H, W, 3)
    if look == HELDOUT:
        img = heldout_post(lrng, lin, sh.scene.light, depth.reshape(H, W), _focus_m(scene))
        q = int(jpeg_quality if jpeg_quality is not None else lrng.integers(60, 92))
    elif look == RANDOMIZED:
        img = randomized_post(lrng, lin, sh.scene.light)
        q = int(jpeg_quality if jpeg_quality is not None else lrng.integers(50, 96))
    else:
        img = _camera_post(rng, lin, scene.light)
        q = int(jpeg_quality if jpeg_quality is not None else rng.integers(72, 96))
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, q])
    rgb = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    lap("post")
    return dict(
        rgb=rgb, jpeg=buf.tobytes(),
        depth=depth.reshape(H, W).astype(np.float32),
        semantic=sem.reshape(H, W), instance=inst.reshape(H, W), rope=rope.reshape(H, W),
        stem=stem.reshape(H, W), z1=z1.reshape(H, W).astype(np.float32), z2=z2.reshape(H, W).astype(np.float32),
        stats=dict(triangles=int(len(F)), aa_pixels=int(n_aa), jpeg_quality=q),
        timings_ms=tm,
    )

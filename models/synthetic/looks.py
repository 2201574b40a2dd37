"""The renderer's looks: the same scenes drawn with another appearance.

``look="randomized"`` (domain randomisation, for training) keeps the default look's procedural
textures and randomises their colours and contrast, the light and the camera response
(:class:`RandomizedShading`, :func:`randomized_light`, :func:`randomized_post`). It uses nothing
of the held-out look below.

``look="heldout"`` (``dbh synth --look heldout``) renders exactly the scenes, labels, depth and
ground truth of the default look (same seed, same geometry), with every appearance model
swapped: bark, foliage, ground and sky cut from the real photos of ``../shared/data/real_trees``
(:class:`PhotoTextures`), another lighting (:func:`heldout_light`) and another camera (tone curve,
saturation, lens blur with depth of field, chromatic aberration, sharpening, colour noise,
:func:`heldout_post`). No training path accepts it (``monodbh.models.training.common.refuse_heldout``):
it measures how the networks hold up on a look they never saw.

Training-only (needs the ``synth`` extra, like the renderer); imported by :mod:`.render`.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from .noise import sample_texture

__all__ = ["LOOKS", "HELDOUT", "PhotoTextures", "photo_textures", "default_texture_folder", "heldout_light",
           "heldout_post", "HeldoutShading", "attribution_text", "RANDOMIZED", "RandomizedShading",
           "randomized_light", "randomized_post", "look_rng"]

#: the looks the renderer knows: ``"default"``; ``"randomized"``, the default one with its colours,
#: textures, light and camera response randomised (domain randomisation, for training); and
#: ``"heldout"``, never trained on
HELDOUT = "heldout"
RANDOMIZED = "randomized"
LOOKS = ("default", RANDOMIZED, HELDOUT)

_HERE = Path(__file__).resolve()
#: the hand-drawn trunk outlines of the real photos (bark is cut inside them)
_OUTLINES = _HERE.parents[2] / "toolkit" / "evaluation" / "data" / "real_trees_outlines.json"


def default_texture_folder() -> Path:
    """``$MONODBH_REAL_TREES``, else ``$MONODBH_SHARED_DATA/real_trees``, else the repository's
    ``../shared/data/real_trees``."""
    if os.environ.get("MONODBH_REAL_TREES"):
        return Path(os.environ["MONODBH_REAL_TREES"])
    if os.environ.get("MONODBH_SHARED_DATA"):
        return Path(os.environ["MONODBH_SHARED_DATA"]) / "real_trees"
    return _HERE.parents[3] / "shared" / "data" / "real_trees"


def _linear(rgb8: np.ndarray) -> np.ndarray:
    """sRGB uint8 (..., 3) -> linear float32."""
    return ((rgb8.astype(np.float32) / 255.0) ** 2.2).astype(np.float32)


def _seamless(patch: np.ndarray) -> np.ndarray:
    """(h, w, 3) -> (2h, 2w, 3) mirrored so that it tiles without seams."""
    top = np.concatenate([patch, patch[:, ::-1]], 1)
    return np.ascontiguousarray(np.concatenate([top, top[::-1]], 0))


@dataclass
class PhotoTextures:
    """Texture patches cut from real photos, linear RGB, each (h, w, 3) float32 tiling seamlessly.

    ``bark``: the outlined trunks unrolled (each row of an outline resampled to a fixed width, the
    shading across the stem divided out); ``foliage``: green, textured patches; ``ground``:
    patches of the photos' lowest quarter; ``sky``: bright blue or white patches of the top.
    ``sources``: the photos used, with their credit and licence (from the outlines file).
    """
    bark: list
    foliage: list
    ground: list
    sky: list
    sources: list


def _bark_strips(rgb: np.ndarray, polygon, width: int = 48) -> list:
    """Unrolled bark strips (rows, width, 3) linear from one trunk outline: each row between the
    outline's borders (the middle 70 %) resampled to ``width``; shading across divided out."""
    H, W = rgb.shape[:2]
    m = np.zeros((H, W), np.uint8)
    cv2.fillPoly(m, [np.round(np.asarray(polygon, np.float64)).astype(np.int32).reshape(-1, 1, 2)], 1)
    rows = []
    lin = _linear(rgb)
    for y in range(H):
        xs = np.nonzero(m[y])[0]
        if len(xs) < 16:
            rows.append(None)
            continue
        a, b = xs[0], xs[-1]
        c, h = 0.5 * (a + b), 0.35 * (b - a)
        xx = np.linspace(c - h, c + h, width).astype(np.float32)
        rows.append(cv2.remap(lin, xx[None], np.full((1, width), y, np.float32), cv2.INTER_LINEAR)[0])
    strips, cur = [], []
    for r in rows + [None]:
        if r is None:
            if len(cur) >= 48:
                strips.append(np.stack(cur))
            cur = []
        else:
            cur.append(r)
    out = []
    for s in strips:
        for k in range(0, len(s) - 47, 96):          # pieces of up to 96 rows
            p = s[k:k + 96]
            col = p.mean((0, 2), keepdims=True) + 1e-4
            p = p / col * col.mean()                 # the light across the stem divided out
            out.append(p.astype(np.float32))
    return out


def _patches(lin: np.ndarray, ok: np.ndarray, size: int, min_frac: float, stride: int) -> list:
    """Square (size, size, 3) patches of ``lin`` where at least ``min_frac`` of ``ok`` (H, W) holds."""
    H, W = ok.shape
    integ = cv2.integral(ok.astype(np.uint8))
    out = []
    for y in range(0, H - size + 1, stride):
        for x in range(0, W - size + 1, stride):
            n = integ[y + size, x + size] - integ[y, x + size] - integ[y + size, x] + integ[y, x]
            if n >= min_frac * size * size:
                out.append(lin[y:y + size, x:x + size].copy())
    return out


def _photo_patches(rgb: np.ndarray, trunks: np.ndarray) -> dict:
    """Foliage, ground and sky patches of one photo (``trunks`` (H, W) bool: the outlines, left out)."""
    H, W = rgb.shape[:2]
    f = rgb.astype(np.float32)
    r, g, b = f[..., 0], f[..., 1], f[..., 2]
    lin = _linear(rgb)
    rows = np.arange(H)[:, None] * np.ones((1, W))
    free = ~cv2.dilate(trunks.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    texture = np.abs(gray - cv2.GaussianBlur(gray, (0, 0), 2.0)) > 4
    skyish = (((b > g) & (g >= r * 0.9) & (b > 120)) | ((r > 200) & (g > 200) & (b > 200)))
    green = (g > r * 1.05) & (g > b * 1.1)
    foliage = green & free & texture & (rows < 0.75 * H) & ~skyish
    ground = free & (rows > 0.75 * H) & ~skyish
    sky = skyish & (rows < 0.45 * H)
    return dict(foliage=_patches(lin, foliage, 32, 0.8, 24), ground=_patches(lin, ground, 48, 0.95, 40),
                sky=_patches(lin, sky, 32, 0.95, 32))


@lru_cache(maxsize=4)
def photo_textures(folder: str | None = None, outlines: str | None = None) -> PhotoTextures:
    """The texture patches of the real photos in ``folder`` (default :func:`default_texture_folder`),
    bark cut inside the trunk outlines of ``outlines`` (default: the shipped outlines file).

    Raises
    ------
    FileNotFoundError
        When the folder or the outlines file is missing, or no photo of the outlines is in it.
    """
    folder = Path(folder) if folder else default_texture_folder()
    outlines = Path(outlines) if outlines else _OUTLINES
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: the real photos for the held-out look are not there "
                                "(set MONODBH_REAL_TREES or MONODBH_SHARED_DATA)")
    photos = json.loads(outlines.read_text())["photos"]
    bank = dict(bark=[], foliage=[], ground=[], sky=[])
    sources = []
    for name in sorted(photos):
        path = folder / name
        if not path.exists():
            continue
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            continue
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        H, W = rgb.shape[:2]
        trunks = np.zeros((H, W), np.uint8)
        for t in photos[name].get("trunks", []):
            bank["bark"] += _bark_strips(rgb, t["polygon"])
            cv2.fillPoly(trunks, [np.round(np.asarray(t["polygon"])).astype(np.int32).reshape(-1, 1, 2)], 1)
        for k, v in _photo_patches(rgb, trunks > 0).items():
            bank[k] += v
        sources.append(dict(photo=name, credit=photos[name].get("credit"), licence=photos[name].get("licence"),
                            source_page=photos[name].get("source_page")))
    if not sources or not all(bank.values()):
        raise FileNotFoundError(f"{folder}: no usable photo of {outlines.name} found for the held-out look")
    return PhotoTextures(bark=[_seamless(p) for p in bank["bark"]], foliage=[_seamless(p) for p in bank["foliage"]],
                         ground=[_seamless(p) for p in bank["ground"]], sky=[_seamless(p) for p in bank["sky"]],
                         sources=sources)


def attribution_text(tex: PhotoTextures) -> str:
    """``ATTRIBUTION.md`` of a folder rendered in the held-out look: its images are made with
    patches of these photos, whose licences ask for the credit, the licence and the source page
    (and, for CC BY-SA, that what is made from them is shared alike)."""
    lines = ["# Attribution", "",
             "The images of this folder were rendered with texture patches (bark, foliage, ground, sky) cut from",
             "the photos below (`../shared/data/real_trees`, credits as its MANIFEST.md gives them). Keep this",
             "file with the images. Images made from CC BY-SA photos are shared under the same licence.", ""]
    for s_ in tex.sources:
        lines.append(f"- `{s_['photo']}`: {s_['credit']}; {s_['licence']}; {s_['source_page']}")
    return "\n".join(lines) + "\n"


def heldout_light(light, rng: np.random.Generator):
    """Another lighting for the same scene: the sun kept where it is, its colour, the sky's, the
    haze's, the exposure and the white balance drawn from other ranges."""
    overcast = float(np.clip(light.overcast * rng.uniform(0.3, 1.0), 0, 1))
    kelvin = rng.uniform(0, 1)                  # 0: warm low sun .. 1: cold blue light
    sun = np.array([1.0, 0.80 + 0.18 * kelvin, 0.55 + 0.45 * kelvin]) * rng.uniform(2.6, 4.6) * (1 - overcast)
    sky = np.array([0.45 + 0.15 * (1 - kelvin), 0.6, 0.95]) * rng.uniform(0.35, 0.7) * (1 - overcast) \
        + np.array([0.85, 0.86, 0.9]) * overcast * rng.uniform(0.8, 1.3)
    return replace(light, sun_rgb=sun, sky_rgb=sky, overcast=overcast,
                   ground_rgb=np.array([0.09, 0.12, 0.06]) * rng.uniform(0.6, 1.5),
                   fog_m=float(rng.uniform(30, 600)), haze_rgb=np.array([0.62, 0.7, 0.82]) * rng.uniform(0.7, 1.2),
                   exposure=float(np.exp(rng.normal(0, 0.4))), wb=np.exp(rng.normal(0, 0.09, 3)))


class HeldoutShading:
    """The appearance hooks of the renderer's shader for the held-out look (mixed into it by
    :func:`.render.render_scene`): photo bark, foliage, ground and sky."""

    def _heldout_init(self, tex: PhotoTextures, rng: np.random.Generator):
        self.ptex = tex
        self.bark_of = {t.id: int(rng.integers(len(tex.bark))) for t in self.scene.trees}
        # a tile (mirrored: twice this) as wide as most stems' visible half-circumference
        self.bark_size_m = {t.id: (rng.uniform(0.35, 0.8), rng.uniform(0.4, 1.2)) for t in self.scene.trees}
        self.bark_offset = {t.id: rng.uniform(0, 1, 2) for t in self.scene.trees}
        self.bark_tint = {t.id: np.exp(rng.normal(0, 0.12, 3)) * rng.uniform(0.7, 1.4) for t in self.scene.trees}
        self.ground_ids = rng.choice(len(tex.ground), size=3, replace=len(tex.ground) < 3)
        self.ground_m = rng.uniform(1.5, 4.0, 3)            # a patch's size on the ground
        ang = rng.uniform(0, np.pi, 3)
        self.ground_rot = np.stack([np.cos(ang), np.sin(ang)], 1)
        self.ground_gain = rng.uniform(0.6, 1.3)
        self.foliage_gain = rng.uniform(0.5, 1.2)
        self.foliage_ids = rng.integers(len(tex.foliage), size=64)
        self.sky_id = int(rng.integers(len(tex.sky)))
        self.sky_gain = rng.uniform(1.2, 2.0)

    def _bark(self, t, th, s):
        tex = self.ptex.bark[self.bark_of[t.id]]
        w_m, h_m = self.bark_size_m[t.id]
        circ = th * t.r_bh
        du, dv = self.bark_offset[t.id]
        alb = sample_texture(tex, circ / (2 * w_m) + du, s / (2 * h_m) + dv) * self.bark_tint[t.id]
        return np.clip(alb * 1.3, 0, 1), np.zeros((len(th), 2))

    def _ground_albedo(self, q):
        def patch(k):
            c, s_ = self.ground_rot[k]
            u = (c * q[:, 0] + s_ * q[:, 1]) / (2 * self.ground_m[k])
            v = (-s_ * q[:, 0] + c * q[:, 1]) / (2 * self.ground_m[k])
            return sample_texture(self.ptex.ground[self.ground_ids[k]], u, v)
        w1 = np.clip((sample_texture(self.tex["coarse"], q[:, 0] / 17.0, q[:, 1] / 17.0) - 0.4) * 4, 0, 1)[:, None]
        w2 = np.clip((sample_texture(self.tex["mid"], q[:, 0] / 9.0, q[:, 1] / 9.0) - 0.55) * 4, 0, 1)[:, None]
        alb = patch(0) * (1 - w1) + patch(1) * w1
        alb = alb * (1 - w2) + patch(2) * w2
        return np.clip(alb * self.ground_gain * 1.2, 0, 1)

    def _foliage_albedo(self, base, prim, p):
        k = self.foliage_ids[(prim * 40503) % len(self.foliage_ids)]
        out = np.empty((len(p), 3))
        for j in np.unique(k):
            m = k == j
            q = p[m]
            out[m] = sample_texture(self.ptex.foliage[j], (q[:, 0] + q[:, 1]) / 0.35, q[:, 2] / 0.35)
        grey = base.mean(1, keepdims=True)       # the object's own brightness, the photo's colour
        return np.clip(out * self.foliage_gain * (0.6 + 4 * grey), 0, 1)

    def _sky(self, light, dirs):
        el = np.clip(dirs[:, 2], -0.2, 1.0)
        az = np.arctan2(dirs[:, 1], dirs[:, 0])
        tex = self.ptex.sky[self.sky_id]
        col = sample_texture(tex, az / (2 * np.pi) * 6, np.clip(el, 0, 1) * 2.0)
        return col * self.sky_gain * (1 - light.overcast) + np.array([0.85, 0.86, 0.9]) * 1.4 * light.overcast


def heldout_post(rng: np.random.Generator, lin: np.ndarray, light, depth: np.ndarray, focus_m: float) -> np.ndarray:
    """Linear HDR image (H, W, 3) -> 8-bit sRGB through another camera than the default's: a
    filmic tone curve, more saturation, lens blur with a depth of field focused at ``focus_m``
    (``depth`` (H, W) metres, 0 for sky), lateral chromatic aberration, sharpening and colour
    noise."""
    H, W = lin.shape[:2]
    lum = lin @ np.array([0.2126, 0.7152, 0.0722])
    key = np.exp(np.mean(np.log(lum + 1e-4)))
    x = lin * (0.18 / key) * light.exposure * light.wb[None, None]
    # filmic curve (Hable), white point 6
    def hable(v):
        A, B, C, D, E, F = 0.22, 0.30, 0.10, 0.20, 0.01, 0.30
        return ((v * (A * v + C * B) + D * E) / (v * (A * v + B) + D * F)) - E / F
    x = hable(2.0 * x) / hable(np.float64(6.0))
    x = np.clip(x, 0, 1) ** (1 / 2.2)
    g = x @ np.array([0.299, 0.587, 0.114])
    x = g[..., None] + (x - g[..., None]) * rng.uniform(1.05, 1.45)          # phone saturation
    img = np.clip(x * 255, 0, 255).astype(np.float32)
    # depth of field: blur grows with |1/z - 1/focus|
    z = np.where(depth > 0, depth, 1e3)
    coc = np.abs(1.0 / z - 1.0 / focus_m) * rng.uniform(2.0, 8.0) * W / 1280
    levels = [img] + [cv2.GaussianBlur(img, (0, 0), s) for s in (1.0, 2.0, 3.5)]
    k = np.clip(coc, 0, 3).astype(np.float32)
    lo = np.floor(k).astype(np.int64)
    fr = (k - lo)[..., None]
    stack = np.stack(levels + [levels[-1]])
    iy, ix = np.mgrid[0:H, 0:W]
    img = stack[lo, iy, ix] * (1 - fr) + stack[np.minimum(lo + 1, 4), iy, ix] * fr
    # lateral chromatic aberration: red and blue scaled about the centre
    ca = rng.uniform(0.0005, 0.002)
    for c, sgn in ((0, 1), (2, -1)):
        sc = 1 + sgn * ca
        M = np.array([[sc, 0, (1 - sc) * W / 2], [0, sc, (1 - sc) * H / 2]], np.float32)
        img[..., c] = cv2.warpAffine(img[..., c], M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    # sharpening halo and colour noise (chroma noise is blotchy, luma noise fine)
    blur = cv2.GaussianBlur(img, (0, 0), 1.2)
    img = img + (img - blur) * rng.uniform(0.3, 1.0)
    luma = rng.normal(0, rng.uniform(1.0, 4.0), (H, W, 1))
    chroma = cv2.GaussianBlur(rng.normal(0, rng.uniform(2.0, 6.0), (H, W, 3)).astype(np.float32), (0, 0), 2.0)
    img = img + luma + chroma
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- randomized look

def look_rng(scene_seed: int, look: str) -> np.random.Generator:
    """The random stream of a look's appearance (the scene's own stream, which fixes its
    geometry and labels, is left as the default look uses it)."""
    return np.random.default_rng([int(scene_seed) & 0xFFFFFFFF, 0x4E1D if look == HELDOUT else 0x7A2B])


def _colour_jitter(rng: np.random.Generator, hue_deg: float, sat: tuple, gain: tuple) -> np.ndarray:
    """(3, 3) linear-RGB matrix: a rotation of the chroma about the grey axis by up to
    ``hue_deg``, its saturation scaled within ``sat`` and the brightness within ``gain``."""
    a = np.deg2rad(rng.uniform(-hue_deg, hue_deg))
    k = np.ones(3) / np.sqrt(3)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
    G = np.outer(k, k)                                   # projection on the grey axis
    S = G + rng.uniform(*sat) * (np.eye(3) - G)
    return rng.uniform(*gain) * (R @ S)


class RandomizedShading:
    """The default shader's appearance with its colours and texture contrast randomised per
    object kind (mixed into the shader by :func:`.render.render_scene`)."""

    def _randomized_init(self, rng: np.random.Generator):
        self.jit_bark = {t.id: _colour_jitter(rng, 60, (0.3, 1.8), (0.5, 1.8)) for t in self.scene.trees}
        self.jit_ground = _colour_jitter(rng, 70, (0.3, 2.0), (0.5, 2.0))
        self.jit_foliage = _colour_jitter(rng, 45, (0.4, 1.8), (0.5, 1.8))
        self.jit_sky = _colour_jitter(rng, 25, (0.5, 1.6), (0.7, 1.4))
        self.tex_amp = rng.uniform(0.0, 0.5, 3)              # extra texture contrast: bark, ground, foliage
        self.tex_scale = rng.uniform(0.05, 2.0, 3)           # and its period (metres)
        self.tex_key = rng.choice(["fine", "mid", "ridge", "ridge2"], 3)

    def _extra(self, k: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        t = sample_texture(self.tex[self.tex_key[k]], u / self.tex_scale[k], v / self.tex_scale[k])
        return (1 - self.tex_amp[k] + 2 * self.tex_amp[k] * t)[:, None]

    def _bark(self, t, th, s):
        alb, bump = super()._bark(t, th, s)
        alb = alb @ self.jit_bark[t.id].T * self._extra(0, th * t.r_bh, s)
        return np.clip(alb, 0, 1), bump

    def _ground_albedo(self, q):
        alb = super()._ground_albedo(q) @ self.jit_ground.T * self._extra(1, q[:, 0], q[:, 1])
        return np.clip(alb, 0, 1)

    def _foliage_albedo(self, base, prim, p):
        alb = super()._foliage_albedo(base, prim, p) @ self.jit_foliage.T * self._extra(2, p[:, 0] + p[:, 1], p[:, 2])
        return np.clip(alb, 0, 1)

    def _sky(self, light, dirs):
        return np.clip(super()._sky(light, dirs) @ self.jit_sky.T, 0, None)


def randomized_light(light, rng: np.random.Generator):
    """The scene's light with wider colours and strengths: sun colour and strength, sky, bounce,
    haze, exposure and white balance redrawn (the sun stays where it is)."""
    warm = rng.uniform(-0.5, 1.5)
    sun = np.array([1.0, 0.93 - 0.12 * warm, 0.82 - 0.25 * warm]).clip(0.3) * rng.uniform(1.5, 4.5) * (1 - light.overcast)
    sky = np.exp(rng.normal(0, 0.15, 3)) * light.sky_rgb * rng.uniform(0.6, 1.5)
    return replace(light, sun_rgb=sun, sky_rgb=sky, ground_rgb=light.ground_rgb * np.exp(rng.normal(0, 0.2, 3)),
                   fog_m=float(np.exp(rng.uniform(np.log(30), np.log(800)))),
                   haze_rgb=light.haze_rgb * np.exp(rng.normal(0, 0.12, 3)) * rng.uniform(0.7, 1.3),
                   exposure=float(np.exp(rng.normal(0, 0.45))), wb=np.exp(rng.normal(0, 0.12, 3)))


def randomized_post(rng: np.random.Generator, lin: np.ndarray, light) -> np.ndarray:
    """Linear HDR image (H, W, 3) -> 8-bit sRGB with a random camera response: exposure key,
    gamma 1.7-2.7, contrast curve, saturation 0.5-1.6, blur 0-1.5 px, sharpening, noise."""
    H, W = lin.shape[:2]
    lum = lin @ np.array([0.2126, 0.7152, 0.0722])
    key = np.exp(np.mean(np.log(lum + 1e-4)))
    x = lin * (rng.uniform(0.12, 0.32) / key) * light.exposure * light.wb[None, None]
    x = 1 - np.exp(-x * rng.uniform(1.0, 2.0))
    x = np.clip(x, 0, 1) ** (1 / rng.uniform(1.7, 2.7))
    c = rng.uniform(-0.6, 0.6)                                       # S-curve (>0) or flat (<0)
    x = x + c * x * (1 - x) * (2 * x - 1)
    g = x @ np.array([0.299, 0.587, 0.114])
    x = g[..., None] + (x - g[..., None]) * rng.uniform(0.5, 1.6)
    img = np.clip(x * 255, 0, 255).astype(np.float32)
    b = rng.uniform(0, 1.5)
    if b > 0.2:
        img = cv2.GaussianBlur(img, (0, 0), b)
    if rng.random() < 0.5:
        img = img + (img - cv2.GaussianBlur(img, (0, 0), 1.5)) * rng.uniform(0.2, 1.2)
    img = img + rng.normal(0, rng.uniform(0.5, 6.0), img.shape)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)

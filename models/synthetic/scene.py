"""Procedural forest scene description: trees, rope, distractors, ground, camera and light.

Everything here is plain numpy and deterministic given a ``numpy.random.Generator``. The
renderer (:mod:`.render`) turns a :class:`Scene` into triangle meshes and rays.

Conventions: world frame in metres with z up; the ground is a gentle height field; a tree's
stem axis is a straight (possibly leaning) line from its base point on the ground, and a
height "along the stem" ``s`` is the arc length from that base. Cross-sections are
perpendicular to the axis. The camera frame is OpenCV's (x right, y down, z forward).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .vec import cross3

__all__ = [
    "SPECIES", "Tree", "Ring", "Camera", "Light", "Scene", "sample_scene",
    "BREAST_HEIGHT_M", "ground_height", "cross_section_shape", "stem_radius_scale",
]

BREAST_HEIGHT_M = 1.3

#: Bark/crown styles. albedo in linear RGB.
SPECIES = {
    "beech": dict(bark=(0.36, 0.36, 0.33), bark_var=0.10, furrow=0.05, conifer=False, birch=False),
    "oak": dict(bark=(0.20, 0.17, 0.14), bark_var=0.25, furrow=0.55, conifer=False, birch=False),
    "pine": dict(bark=(0.30, 0.17, 0.10), bark_var=0.25, furrow=0.45, conifer=True, birch=False),
    "spruce": dict(bark=(0.22, 0.15, 0.11), bark_var=0.20, furrow=0.25, conifer=True, birch=False),
    "birch": dict(bark=(0.72, 0.71, 0.66), bark_var=0.10, furrow=0.05, conifer=False, birch=True),
    "maple": dict(bark=(0.26, 0.24, 0.21), bark_var=0.20, furrow=0.30, conifer=False, birch=False),
}


def ground_height(params: dict, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Ground height z(x, y) in metres: a plane tilt plus a few smooth undulations.

    Parameters
    ----------
    params : dict with ``slope`` (2,), ``waves`` (K, 4) rows of (amp, kx, ky, phase).
    x, y : arrays of the same shape (metres).
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    z = params["slope"][0] * x + params["slope"][1] * y
    for amp, kx, ky, ph in params["waves"]:
        z = z + amp * np.sin(kx * x + ky * y + ph)
    return z


@dataclass
class Ring:
    """A band tied around a stem: the red rope or a flagging tape.

    Attributes
    ----------
    s_m : height along the stem of the band's centre line (metres).
    tube_radius_m : radius of the rope tube, or half the thickness of a tape.
    width_m : tape width along the stem (0 for a round rope).
    rgb : linear albedo.
    is_rope : True for the red measuring rope.
    knot : whether a knot and hanging ends are present.
    knot_theta : angle of the knot around the stem (radians, in the stem frame).
    tail_len_m : length of the hanging ends.
    """
    s_m: float
    tube_radius_m: float
    width_m: float
    rgb: tuple
    is_rope: bool
    knot: bool = False
    knot_theta: float = 0.0
    tail_len_m: float = 0.0


def cross_section_shape(theta: np.ndarray, axis_ratio: float, ell_phase: float, harmonics) -> np.ndarray:
    """Relative radius ``(N,)`` of a stem's cross-section at angles ``theta`` (radians): an
    ellipse with semi-axes 1 and ``axis_ratio`` turned by ``ell_phase``, times ``1 + amp
    cos(order theta + phase)`` for each ``(order, amp, phase)`` row of ``harmonics``."""
    theta = np.asarray(theta, np.float64)
    c = np.cos(theta - ell_phase)
    sn = np.sin(theta - ell_phase)
    q = axis_ratio
    r = q / np.sqrt((q * c) ** 2 + sn ** 2)      # ellipse with semi-axes 1 and q
    for order, amp, ph in harmonics:
        r = r * (1.0 + amp * np.cos(order * theta + ph))
    return r


def stem_radius_scale(s: np.ndarray, r_bh: float, taper: float, flare: float, height_m: float) -> np.ndarray:
    """Radius scale (metres) at heights ``s`` along a stem; tapers to a point at the top."""
    s = np.asarray(s, np.float64)
    r = r_bh * (1.0 - taper * (s - BREAST_HEIGHT_M))
    r = r * (1.0 + flare * np.exp(-np.clip(s, 0, None) / 0.25))
    top = np.clip((height_m - s) / (0.35 * height_m), 0.0, 1.0)
    r = r * (0.15 + 0.85 * top) * np.where(s > height_m, 0.0, 1.0)
    return np.maximum(r, 0.004)


@dataclass
class Tree:
    """One tree; the stem cross-section radius is ``r(theta, s) = base_r(s) * shape(theta)``."""
    id: int
    species: str
    base: np.ndarray            # (3,) ground point of the stem axis
    axis: np.ndarray            # (3,) unit stem direction
    e1: np.ndarray              # (3,) unit, perpendicular to axis
    e2: np.ndarray              # (3,) unit, axis x e1
    r_bh: float                 # scale radius at breast height (metres)
    axis_ratio: float           # ellipse minor/major
    ell_phase: float            # ellipse orientation (radians)
    harmonics: np.ndarray       # (K, 3) rows (order, amplitude, phase)
    flare: float                # root flare amplitude
    taper: float                # relative radius loss per metre
    height_m: float
    crown_base_m: float
    crown_radius_m: float
    lod: int                    # 0 near/detailed, 1 mid, 2 far
    crown_density: float = 1.0  # leaf clusters and leaves per cluster, relative (open-grown: 4-10)
    leaf_scale: float = 1.0     # leaf size, relative (open-grown: 1.3-2.2, clumps of leaves)
    bark_tint: tuple = (1.0, 1.0, 1.0)
    leaf_rgb: tuple = (0.08, 0.16, 0.04)
    dead: bool = False          # a dead snag: no foliage
    rings: list = field(default_factory=list)
    paint: dict | None = None   # red paint mark: theta0, dtheta, s0, s1
    branches: list = field(default_factory=list)  # (s, theta, elev, length, radius)
    seed: int = 0
    _perimeter_cache: dict = field(default_factory=dict, repr=False, compare=False)

    # ----------------------------------------------------------------- geometry
    def shape(self, theta: np.ndarray) -> np.ndarray:
        """Relative radius of the cross-section at angle ``theta`` (radians), ``(N,)``."""
        return cross_section_shape(theta, self.axis_ratio, self.ell_phase, self.harmonics)

    def base_r(self, s: np.ndarray) -> np.ndarray:
        """Radius scale along the stem (metres); tapers to a point at the top."""
        return stem_radius_scale(s, self.r_bh, self.taper, self.flare, self.height_m)

    def radius(self, theta: np.ndarray, s: np.ndarray) -> np.ndarray:
        return self.base_r(s) * self.shape(theta)

    def surface_point(self, theta: np.ndarray, s: np.ndarray, offset: float = 0.0) -> np.ndarray:
        """World points on the stem surface, ``(N, 3)``; ``offset`` pushes outward (metres)."""
        theta = np.asarray(theta, np.float64)
        s = np.broadcast_to(np.asarray(s, np.float64), theta.shape)
        r = self.radius(theta, s) + offset
        return (self.base[None] + s[:, None] * self.axis[None]
                + (r * np.cos(theta))[:, None] * self.e1[None]
                + (r * np.sin(theta))[:, None] * self.e2[None])

    def axis_point(self, s: float) -> np.ndarray:
        return self.base + s * self.axis

    def perimeter_m(self, s: float = BREAST_HEIGHT_M, n: int = 512, segments: int | None = None) -> float:
        """Perimeter of the cross-section at ``s``: the continuous curve (``segments=None``)
        or the rendered polygon with ``segments`` vertices."""
        m = n if segments is None else segments
        key = (float(s), m, self.r_bh, self.taper, self.flare, self.axis_ratio, self.ell_phase,
               np.asarray(self.harmonics).tobytes())
        hit = self._perimeter_cache.get(key)
        if hit is not None:
            return hit
        th = np.linspace(0, 2 * np.pi, m, endpoint=False)
        r = self.radius(th, np.full_like(th, s))
        x, y = r * np.cos(th), r * np.sin(th)
        out = float(np.hypot(np.diff(np.r_[x, x[0]]), np.diff(np.r_[y, y[0]])).sum())
        self._perimeter_cache[key] = out
        return out

    def dbh_m(self, segments: int | None = None) -> float:
        """Tape DBH: perimeter at 1.3 m along the stem divided by pi."""
        return self.perimeter_m(BREAST_HEIGHT_M, segments=segments) / np.pi

    def segments(self) -> int:
        return (64 if self.id == 1 else 40, 20, 10)[self.lod]


@dataclass
class Camera:
    """Pinhole camera with OpenCV distortion, placed in the world."""
    width: int
    height: int
    K: np.ndarray               # (3, 3)
    dist: np.ndarray            # (5,) k1 k2 p1 p2 k3
    R_wc: np.ndarray            # (3, 3) world-from-camera rotation (columns: x, y, z axes)
    t_wc: np.ndarray            # (3,) camera centre in world
    height_m: float
    pitch_deg: float
    roll_deg: float
    yaw_deg: float


@dataclass
class Light:
    sun_dir: np.ndarray         # (3,) unit vector towards the sun
    sun_rgb: np.ndarray         # (3,) irradiance
    sky_rgb: np.ndarray         # (3,) ambient from the sky
    ground_rgb: np.ndarray      # (3,) bounce light
    overcast: float             # 0 clear .. 1 overcast
    fog_m: float                # distance scale of aerial haze
    haze_rgb: np.ndarray
    exposure: float
    wb: np.ndarray              # (3,) white-balance gains


@dataclass
class Scene:
    trees: list
    camera: Camera
    light: Light
    ground: dict
    roped_tree: int | None
    bushes: list                # (center (3,), radius, rgb, red)
    grass: list                 # patches: (center (2,), radius, density, height)
    logs: list                  # dead wood: (p0 (3,), p1 (3,), radius)
    person: dict | None
    distractors: list
    seed: int
    textures: dict = field(default_factory=dict)
    stand: str = "forest"       # "forest" or "park" (:data:`STANDS`; "mixed" picks one per scene)
    view: str = "level"         # "level", "upward" or "protocol" (:data:`VIEWS`; "mixed" picks one per scene)


# --------------------------------------------------------------------------- sampling
def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _frame(axis):
    """Two unit vectors perpendicular to ``axis`` (e1 roughly horizontal)."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = _unit(cross3(ref, axis))
    e2 = cross3(axis, e1)
    return e1, e2


def _make_tree(rng, tid, xy, ground, species=None, dbh=None, lod=0):
    species = species or rng.choice(list(SPECIES))
    sp = SPECIES[species]
    if dbh is None:
        dbh = float(np.clip(rng.lognormal(np.log(0.26), 0.45), 0.06, 0.9))
    lean = np.deg2rad(rng.uniform(0, 4.0) if rng.random() < 0.8 else rng.uniform(4.0, 9.0))
    az = rng.uniform(0, 2 * np.pi)
    axis = _unit([np.sin(lean) * np.cos(az), np.sin(lean) * np.sin(az), np.cos(lean)])
    e1, e2 = _frame(axis)
    z = float(ground_height(ground, xy[0], xy[1]))
    q = float(rng.uniform(0.82, 1.0)) if rng.random() < 0.85 else float(rng.uniform(0.72, 0.82))
    nh = rng.integers(0, 4)
    harm = np.array([[k, rng.uniform(0, 0.02 + 0.02 * sp["furrow"]), rng.uniform(0, 2 * np.pi)]
                     for k in rng.choice([3, 4, 5, 6, 7], size=nh, replace=False)]).reshape(-1, 3)
    height = float(np.clip(dbh * rng.uniform(55, 110) + rng.uniform(3, 8), 4, 38))
    conifer = sp["conifer"]
    crown_base = float(height * (rng.uniform(0.1, 0.45) if species == "spruce" else rng.uniform(0.25, 0.6)))
    crown_r = float(np.clip(dbh * rng.uniform(8, 16), 0.8, 6.0) * (0.6 if conifer else 1.0))
    t = Tree(
        id=tid, species=str(species), base=np.array([xy[0], xy[1], z]), axis=axis, e1=e1, e2=e2,
        r_bh=dbh / 2.0, axis_ratio=q, ell_phase=float(rng.uniform(0, np.pi)), harmonics=harm,
        flare=float(rng.uniform(0.0, 0.5) if rng.random() < 0.6 else 0.0),
        taper=float(rng.uniform(0.01, 0.035)), height_m=height, crown_base_m=crown_base,
        crown_radius_m=crown_r, lod=lod,
        bark_tint=tuple(rng.uniform(0.8, 1.2, 3) * rng.uniform(0.75, 1.25)),
        leaf_rgb=tuple(np.array([rng.uniform(0.03, 0.12), rng.uniform(0.10, 0.22), rng.uniform(0.02, 0.06)])),
        dead=bool(rng.random() < 0.05), seed=int(rng.integers(1 << 30)),
    )
    # scale r_bh so that the tape DBH (perimeter / pi) equals the sampled dbh exactly
    k = dbh / t.dbh_m()
    t.r_bh *= k
    # the cross-section at 1.3 m scales with r_bh: its perimeters are known without integrating
    t._perimeter_cache = {(key[0], key[1], t.r_bh) + key[3:]: v * k
                          for key, v in t._perimeter_cache.items()}
    nb = int(rng.integers(2, 9)) if not conifer else int(rng.integers(6, 16))
    for _ in range(nb if lod < 2 else 0):
        s = rng.uniform(max(1.8, crown_base * 0.6), height * 0.9)
        if conifer and rng.random() < 0.5:
            s = rng.uniform(1.6, max(1.7, crown_base))       # dead lower branches of conifers
        t.branches.append((float(s), float(rng.uniform(0, 2 * np.pi)),
                           float(np.deg2rad(rng.uniform(-10, 50))),
                           float(rng.uniform(0.5, 1.0) * crown_r), float(max(0.01, rng.uniform(0.1, 0.3) * t.r_bh))))
    return t


def _rope_color(rng):
    # linear RGB from orange-red to dark red
    h = rng.uniform(0.0, 1.0)
    r = rng.uniform(0.35, 0.75)
    return (r, r * (0.02 + 0.18 * h), r * rng.uniform(0.02, 0.08))


def _tape_color(rng):
    # fluorescent orange flagging tape, linear RGB: G/R 0.28-0.5 is sRGB hue ~33-44 degrees,
    # clearly more orange than the rope (sRGB hue ~10-29 degrees, see _rope_color)
    r = rng.uniform(0.7, 0.9)
    return (r, r * rng.uniform(0.28, 0.5), r * rng.uniform(0.0, 0.03))


#: the kinds of 1.3 m marker the generator renders (``sample_scene(marker=...)``)
MARKERS = ("rope", "strap", "mixed")
#: the kinds of stand the generator renders (``sample_scene(stand=...)``)
STANDS = ("forest", "park", "mixed")
#: what grows round the roped stem's foot (``sample_scene(foot=...)``): the stand's own draws,
#: grass tufts there on every scene and a low bush beside it on 40 % (``"clutter"``), or grass as
#: likely over as under the stem-base label's 0.3 m and a bush in front of the foot on 35 %
#: (``"hidden"``)
FEET = ("plain", "clutter", "hidden")
#: how the camera looks at the main tree (``sample_scene(view=...)``): level at about breast
#: height, up its trunk into the crown from close by, upward on a third of the scenes, or as the
#: README's "Taking the photo" asks (:func:`_as_instructed`)
VIEWS = ("level", "upward", "mixed", "protocol")
#: the photo as instructed: the camera's distance from the roped stem (m), and the marker at
#: least this thick on the photo (pixels; README, "Taking the photo")
PROTOCOL_DISTANCE_M = (2.0, 6.0)
PROTOCOL_MARKER_MIN_PX = 5.0
#: a strap's width along the stem (m): flagging tape wound in a few turns or webbing
STRAP_WIDTH_RANGE_M = (0.02, 0.05)


def sample_scene(rng: np.random.Generator, width: int, height: int, *, distortion: bool = True,
                 seed: int = 0, marker: str = "rope", stand: str = "forest", foot: str = "plain",
                 view: str = "level") -> Scene:
    """Sample a random forest scene and a handheld camera looking at a (usually roped) tree.

    Parameters
    ----------
    rng : numpy.random.Generator
    width, height : image size in pixels.
    distortion : give the camera random radial distortion (else a pinhole).
    marker : the roped tree's marker (:data:`MARKERS`): a round rope 5-15 mm thick, a flat red
        strap of :data:`STRAP_WIDTH_RANGE_M` (2 mm thick), or either at random. The strap's
        draws come from their own generator, so a scene differs from its ``"rope"`` twin in the
        marker only.
    stand : ``"forest"`` (the default: a closed stand of poles and sparse crowns), ``"park"``
        (open-grown trees with dense, low crowns on a lawn, seen from 3-25 m, as in most openly
        licensed tree photos; :func:`_to_park`) or ``"mixed"`` (either, half and half). The park's
        draws come from their own generator, so ``"forest"`` scenes are the same with any value.
    foot : ``"plain"`` (the default), ``"clutter"``: 1-3 grass tufts round the main stem's foot
        and, on 40 % of scenes, a low bush 0.3-1.0 m from it (:func:`_foot_clutter`, the
        stem-base network's hard cases), or ``"hidden"``: tufts 0.05-0.6 m high (a foot in grass
        over 0.3 m is labelled hidden) and, on 35 %, a bush between the camera and the foot
        (:func:`_foot_hidden`: the tops of what hides a foot, which the network must not take
        for it). The clutter's draws come from their own generator, so the scene's other objects
        are the same (the render's texture draws are not).
    view : ``"level"`` (the default: the camera looks at the main tree from -15 to +28 degrees of
        pitch), ``"upward"``: from 1-5 m away, up the trunk into the crown, 30-70 degrees up
        (:func:`_look_up`; trunk training, as in many openly licensed tree photos), ``"mixed"``
        (upward on a third of the scenes), or ``"protocol"``: the photo README's "Taking the
        photo" asks for (:func:`_as_instructed`: roped with an 8-15 mm rope or the scene's strap,
        the knot toward or away from the camera, 2-6 m away, rope and foot in the frame). Its
        draws come from their own generator, so the scene's objects are those of ``"level"``.

    Returns
    -------
    Scene
    """
    if marker not in MARKERS:
        raise ValueError(f"marker must be one of {MARKERS}, got {marker!r}")
    if stand not in STANDS:
        raise ValueError(f"stand must be one of {STANDS}, got {stand!r}")
    if foot not in FEET:
        raise ValueError(f"foot must be one of {FEET}, got {foot!r}")
    if view not in VIEWS:
        raise ValueError(f"view must be one of {VIEWS}, got {view!r}")
    slope = rng.normal(0, 0.04, 2) * (rng.random() < 0.7)
    waves = np.array([[rng.uniform(0, 0.25), rng.normal(0, 0.15), rng.normal(0, 0.15), rng.uniform(0, 6.3)]
                      for _ in range(3)])
    ground = dict(slope=slope, waves=waves)

    # ---- the main tree at the origin; camera placed relative to it
    main_dbh = float(np.clip(rng.lognormal(np.log(0.28), 0.4), 0.08, 0.8))
    trees = [_make_tree(rng, 1, (0.0, 0.0), ground, dbh=main_dbh, lod=0)]
    main = trees[0]

    dist_h = float(np.exp(rng.uniform(np.log(1.5), np.log(12.0))))
    cam_az = rng.uniform(0, 2 * np.pi)
    cam_xy = np.array([dist_h * np.cos(cam_az), dist_h * np.sin(cam_az)])
    cam_h = float(rng.uniform(1.1, 1.9))
    cam_pos = np.array([cam_xy[0], cam_xy[1], float(ground_height(ground, *cam_xy)) + cam_h])

    # ---- stand
    plantation = rng.random() < 0.35
    species_pool = list(rng.choice(list(SPECIES), size=int(rng.integers(1, 4)), replace=False))
    if main.species not in species_pool:
        species_pool.append(main.species)
    R_area = 32.0
    pts = []
    if plantation:
        sp_ = rng.uniform(2.0, 4.5)
        ang = rng.uniform(0, np.pi)
        c, s = np.cos(ang), np.sin(ang)
        g = np.arange(-R_area, R_area + 1e-6, sp_)
        gx, gy = np.meshgrid(g, g * rng.uniform(0.8, 1.5))
        p = np.stack([gx.ravel(), gy.ravel()], 1) + rng.normal(0, 0.25, (gx.size, 2))
        p = p @ np.array([[c, -s], [s, c]])
        pts = [q for q in p if np.hypot(*q) < R_area]
        species_pool = species_pool[:1]
    else:
        density = rng.uniform(0.012, 0.07)     # stems per m^2 (120..700 / ha)
        n = rng.poisson(density * np.pi * R_area ** 2)
        rr = R_area * np.sqrt(rng.random(n))
        aa = rng.uniform(0, 2 * np.pi, n)
        pts = list(np.stack([rr * np.cos(aa), rr * np.sin(aa)], 1))
    pts = pts[:260]
    cam_dir_h = -cam_xy / dist_h                 # horizontal direction camera -> main tree
    occluder_budget = 1 if rng.random() < 0.25 else 0
    for q in pts:
        q = np.asarray(q, np.float64)
        if np.hypot(*q) < 1.2 or np.hypot(*(q - cam_xy)) < 1.0:
            continue
        # keep the line of sight to the main tree mostly clear
        rel = q - cam_xy
        along = rel @ cam_dir_h
        perp = abs(rel[0] * cam_dir_h[1] - rel[1] * cam_dir_h[0])
        if 0 < along < dist_h + 0.5 and perp < main.r_bh + 0.35:
            if occluder_budget and along < dist_h - 0.8 and perp > 0.5 * main.r_bh:
                occluder_budget -= 1
                t = _make_tree(rng, len(trees) + 1, q, ground, species=rng.choice(species_pool),
                               dbh=float(rng.uniform(0.05, 0.12)), lod=0)
                trees.append(t)
            continue
        d_cam = np.hypot(*(q - cam_xy))
        lod = 0 if d_cam < 8 else (1 if d_cam < 18 else 2)
        if plantation:
            dbh = float(np.clip(main_dbh * rng.normal(1.0, 0.12), 0.06, 0.9))
        else:
            dbh = None
        trees.append(_make_tree(rng, len(trees) + 1, q, ground, species=rng.choice(species_pool),
                                dbh=dbh, lod=lod))
    if plantation:
        for t in trees[1:]:
            t.species = main.species
    # understory: saplings with low crowns
    for _ in range(int(rng.integers(0, 18))):
        q = cam_xy + rng.normal(0, 9, 2)
        rel = q - cam_xy
        along = rel @ cam_dir_h
        perp = abs(rel[0] * cam_dir_h[1] - rel[1] * cam_dir_h[0])
        if (0 < along < dist_h + 0.5 and perp < main.r_bh + 0.4) or np.hypot(*rel) < 1.0 or np.hypot(*q) < 0.8:
            continue
        d_cam = np.hypot(*rel)
        t = _make_tree(rng, len(trees) + 1, q, ground, species=rng.choice(species_pool),
                       dbh=float(rng.uniform(0.02, 0.07)), lod=0 if d_cam < 8 else 1)
        t.height_m = float(rng.uniform(2.0, 7.0))
        t.crown_base_m = float(rng.uniform(0.4, 1.5))
        t.crown_radius_m = float(rng.uniform(0.5, 1.5))
        t.branches = []
        trees.append(t)

    # ---- rope and distractors
    distractors = []
    roped = None
    if rng.random() < 0.9:
        roped = 1
        main.rings.append(Ring(s_m=BREAST_HEIGHT_M, tube_radius_m=float(rng.uniform(0.0025, 0.0075)),
                               width_m=0.0, rgb=_rope_color(rng), is_rope=True,
                               knot=bool(rng.random() < 0.5), knot_theta=float(rng.uniform(0, 2 * np.pi)),
                               tail_len_m=float(rng.uniform(0.05, 0.3))))
        mrng = np.random.default_rng([int(seed), 1301])
        if marker == "strap" or (marker == "mixed" and mrng.random() < 0.5):
            ring = main.rings[-1]
            ring.width_m = float(mrng.uniform(*STRAP_WIDTH_RANGE_M))
            ring.tube_radius_m = 0.001
    near = [t for t in trees[1:] if t.lod == 0]
    far = [t for t in trees[1:] if t.lod < 2 and np.hypot(*(t.base[:2] - cam_xy)) > dist_h + 3]
    if near and rng.random() < 0.25:
        t = near[rng.integers(len(near))]
        h = float(rng.choice([rng.uniform(0.3, 0.8), rng.uniform(1.9, 2.6)]))
        t.rings.append(Ring(s_m=h, tube_radius_m=0.0008, width_m=float(rng.uniform(0.02, 0.035)),
                            rgb=_tape_color(rng), is_rope=False,
                            knot=bool(rng.random() < 0.6), knot_theta=float(rng.uniform(0, 6.28)),
                            tail_len_m=float(rng.uniform(0.1, 0.4))))
        distractors.append(dict(kind="flagging_tape", tree=t.id, height_m=h))
    if near and rng.random() < 0.2:
        t = near[rng.integers(len(near))]
        s0 = float(rng.uniform(0.8, 2.0))
        t.paint = dict(theta0=float(rng.uniform(0, 6.28)), dtheta=float(rng.uniform(0.15, 0.5)),
                       s0=s0, s1=s0 + float(rng.choice([rng.uniform(0.05, 0.12), rng.uniform(0.2, 0.5)])),
                       rgb=_rope_color(rng))
        distractors.append(dict(kind="paint_mark", tree=t.id, height_m=s0))
    if far and roped and rng.random() < 0.1:
        t = far[rng.integers(len(far))]
        t.rings.append(Ring(s_m=BREAST_HEIGHT_M, tube_radius_m=0.004, width_m=0.0, rgb=_rope_color(rng),
                            is_rope=True))
        distractors.append(dict(kind="second_rope", tree=t.id, height_m=BREAST_HEIGHT_M))

    bushes = []
    for _ in range(int(rng.integers(0, 14))):
        d = rng.uniform(1.0, 25.0)
        a = rng.uniform(0, 2 * np.pi)
        c = cam_xy + d * np.array([np.cos(a), np.sin(a)])
        if rng.random() < 0.3:              # bushes near the main trunk base hide it partly
            c = main.base[:2] + rng.normal(0, 0.6, 2)
        r = float(rng.uniform(0.25, 0.9))
        zc = float(ground_height(ground, *c)) + r * 0.5
        red = bool(rng.random() < 0.06)
        rgb = (0.25, 0.02, 0.015) if red else (rng.uniform(0.03, 0.1), rng.uniform(0.1, 0.22), rng.uniform(0.02, 0.05))
        bushes.append((np.array([c[0], c[1], zc]), r, rgb, red))
        if red:
            distractors.append(dict(kind="red_leaves"))
    grass = []
    for _ in range(int(rng.integers(0, 8))):
        c = cam_xy + rng.normal(0, 6, 2) if rng.random() < 0.6 else main.base[:2] + rng.normal(0, 1.0, 2)
        grass.append((c, float(rng.uniform(0.5, 3.0)), float(rng.uniform(80, 400)), float(rng.uniform(0.1, 0.45))))
    logs = []
    for _ in range(int(rng.integers(0, 4))):
        c = cam_xy + rng.normal(0, 8, 2)
        a = rng.uniform(0, np.pi)
        L = rng.uniform(1.0, 5.0)
        r = rng.uniform(0.05, 0.2)
        p0 = np.array([c[0], c[1], 0.0])
        p1 = p0 + L * np.array([np.cos(a), np.sin(a), 0.0])
        p0[2] = ground_height(ground, p0[0], p0[1]) + r * 0.7
        p1[2] = ground_height(ground, p1[0], p1[1]) + r * 0.7
        logs.append((p0, p1, r))
    person = None
    if rng.random() < 0.08:
        d = rng.uniform(2.0, 12.0)
        a = cam_az + np.pi + rng.uniform(-0.6, 0.6)
        c = cam_xy + d * np.array([np.cos(a), np.sin(a)])
        person = dict(center=np.array([c[0], c[1], float(ground_height(ground, *c))]),
                      jacket=_rope_color(rng), height=float(rng.uniform(1.6, 1.9)))
        distractors.append(dict(kind="red_jacket"))

    # ---- camera
    W, H = width, height
    fov = np.deg2rad(rng.uniform(55, 80))
    f = (max(W, H) / 2.0) / np.tan(fov / 2)
    K = np.array([[f, 0, (W - 1) / 2 + rng.normal(0, 0.01 * W)],
                  [0, f, (H - 1) / 2 + rng.normal(0, 0.01 * H)],
                  [0, 0, 1.0]])
    if distortion:
        dist = np.array([rng.uniform(-0.08, 0.05), rng.uniform(-0.03, 0.05), rng.normal(0, 3e-4), rng.normal(0, 3e-4), 0.0])
    else:
        dist = np.zeros(5)
    target = main.axis_point(BREAST_HEIGHT_M if roped else rng.uniform(0.8, 2.0))
    for _attempt in range(50):
        pitch = np.deg2rad(rng.uniform(-15, 20))
        roll = np.deg2rad(rng.uniform(-6, 6))
        # choose yaw so that the target falls at a random column of the frame
        rel = target - cam_pos
        yaw0 = np.arctan2(rel[1], rel[0])
        u_frac = rng.uniform(0.12, 0.88)
        yaw = yaw0 + np.arctan((u_frac - 0.5) * W / f) * (1.0 if True else -1.0)
        Rwc = _rotation(yaw, pitch, roll)
        pc = Rwc.T @ (target - cam_pos)
        if pc[2] <= 0.5:
            continue
        u = K[0, 0] * pc[0] / pc[2] + K[0, 2]
        v = K[1, 1] * pc[1] / pc[2] + K[1, 2]
        if 0.08 * W < u < 0.92 * W and 0.08 * H < v < 0.92 * H:
            break
    cam = Camera(width=W, height=H, K=K, dist=dist, R_wc=Rwc, t_wc=cam_pos, height_m=cam_h,
                 pitch_deg=float(np.rad2deg(pitch)), roll_deg=float(np.rad2deg(roll)),
                 yaw_deg=float(np.rad2deg(yaw)))

    # ---- light
    overcast = float(rng.random() < 0.35) * rng.uniform(0.6, 1.0)
    sun_el = np.deg2rad(rng.uniform(12, 65))
    sun_az = rng.uniform(0, 2 * np.pi)
    if rng.random() < 0.2:                  # backlight: sun roughly ahead of the camera
        sun_az = np.deg2rad(cam.yaw_deg) + rng.uniform(-0.5, 0.5)
        sun_el = np.deg2rad(rng.uniform(10, 35))
    sun_dir = np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
    warm = rng.uniform(0, 1)
    sun_rgb = np.array([1.0, 0.93 - 0.1 * warm, 0.82 - 0.2 * warm]) * rng.uniform(2.2, 3.6) * (1 - overcast)
    sky_rgb = np.array([0.55, 0.65, 0.85]) * rng.uniform(0.5, 0.8) * (1 - overcast) + np.array([0.8, 0.82, 0.85]) * overcast * rng.uniform(0.9, 1.4)
    light = Light(sun_dir=sun_dir, sun_rgb=sun_rgb, sky_rgb=sky_rgb,
                  ground_rgb=np.array([0.12, 0.11, 0.08]) * rng.uniform(0.6, 1.3),
                  overcast=overcast, fog_m=float(rng.uniform(50, 250)),
                  haze_rgb=np.array([0.6, 0.66, 0.72]) * rng.uniform(0.6, 1.1),
                  exposure=float(np.exp(rng.normal(0, 0.25))),
                  wb=np.exp(rng.normal(0, 0.05, 3)))
    scene = Scene(trees=trees, camera=cam, light=light, ground=ground, roped_tree=roped,
                  bushes=bushes, grass=grass, logs=logs, person=person,
                  distractors=distractors, seed=seed)
    prng = np.random.default_rng([int(seed), 7001])
    if stand == "park" or (stand == "mixed" and prng.random() < 0.5):
        _to_park(scene, prng)
    if foot == "clutter":
        _foot_clutter(scene, np.random.default_rng([int(seed), 7002]))
    elif foot == "hidden":
        _foot_hidden(scene, np.random.default_rng([int(seed), 7003]))
    vrng = np.random.default_rng([int(seed), 7004])
    if view == "upward" or (view == "mixed" and vrng.random() < 1 / 3):
        _look_up(scene, vrng)
    elif view == "protocol":
        _as_instructed(scene, np.random.default_rng([int(seed), 7005]))
    return scene


def _as_instructed(scene: Scene, rng: np.random.Generator) -> None:
    """The photo README's "Taking the photo" asks for, in place: the main tree roped at 1.3 m (a
    rope of 8-15 mm; a strap keeps its width), the knot turned toward or away from the camera
    (within 30 degrees), the camera held 1.2-1.8 m above the ground :data:`PROTOCOL_DISTANCE_M`
    from the stem's axis (no farther than where the marker is :data:`PROTOCOL_MARKER_MIN_PX`
    thick, at least 2.5 m), on a line of sight clear of other stems, the stem at 30-70 % of the
    frame's width with the rope and the stem's foot in the frame, rolled at most 4 degrees.
    Grass and bushes at the foot stay where the stand put them. Draws only from ``rng``."""
    main = scene.trees[0]
    ring = next((r for r in main.rings if r.is_rope), None)
    if ring is None:
        ring = Ring(s_m=BREAST_HEIGHT_M, tube_radius_m=0.005, width_m=0.0, rgb=_rope_color(rng), is_rope=True,
                    knot=bool(rng.random() < 0.5), tail_len_m=float(rng.uniform(0.05, 0.3)))
        main.rings.append(ring)
        scene.roped_tree = main.id
    if ring.width_m == 0.0:
        ring.tube_radius_m = float(rng.uniform(0.004, 0.0075))
    marker_m = max(ring.width_m, 2 * ring.tube_radius_m)
    cam = scene.camera
    W, H, K = cam.width, cam.height, cam.K
    d_lo, d_hi = PROTOCOL_DISTANCE_M
    d_hi = min(d_hi, max(2.5, K[0, 0] * marker_m / PROTOCOL_MARKER_MIN_PX))
    others = scene.trees[1:]
    rel0 = cam.t_wc[:2] - main.base[:2]
    az0 = float(np.arctan2(rel0[1], rel0[0]))            # first try: where the stand put the camera
    for attempt in range(200):
        az = az0 if attempt == 0 else rng.uniform(0, 2 * np.pi)
        d = float(rng.uniform(d_lo, d_hi))
        xy = main.base[:2] + d * np.array([np.cos(az), np.sin(az)])
        to_stem = (main.base[:2] - xy) / d
        blocked = False
        for t in others:
            rel = t.base[:2] - xy
            along = float(rel @ to_stem)
            perp = abs(rel[0] * to_stem[1] - rel[1] * to_stem[0])
            if np.hypot(*rel) < t.r_bh + 0.5 or (0 < along < d and perp < t.r_bh + main.r_bh + 0.1):
                blocked = True
                break
        if blocked or any(np.hypot(*(b[0][:2] - xy)) < b[1] + 0.3 for b in scene.bushes):
            continue
        h = float(rng.uniform(1.2, 1.8))
        pos = np.array([xy[0], xy[1], float(ground_height(scene.ground, *xy)) + h])
        rel = main.axis_point(rng.uniform(0.4, 0.9)) - pos
        pitch = float(np.arctan2(rel[2], np.hypot(rel[0], rel[1])) + np.deg2rad(rng.normal(0, 3)))
        yaw = np.arctan2(rel[1], rel[0]) + np.arctan((rng.uniform(0.3, 0.7) - 0.5) * W / K[0, 0])
        roll = np.deg2rad(rng.uniform(-4, 4))
        Rwc = _rotation(yaw, pitch, roll)
        pc = (main.base[None] + np.array([[0.0], [BREAST_HEIGHT_M]]) * main.axis[None] - pos) @ Rwc
        if (pc[:, 2] <= 0.5).any():
            continue
        u, v = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
        if not ((0.08 * H < v) & (v < 0.92 * H) & (0.15 * W < u) & (u < 0.85 * W)).all():
            continue
        cam_dir = pos - main.axis_point(BREAST_HEIGHT_M)
        ring.knot_theta = float(np.arctan2(cam_dir @ main.e2, cam_dir @ main.e1) + np.pi * (rng.random() < 0.5)
                                + np.deg2rad(rng.uniform(-30, 30)))
        scene.camera = Camera(width=W, height=H, K=K, dist=cam.dist, R_wc=Rwc, t_wc=pos, height_m=h,
                              pitch_deg=float(np.rad2deg(pitch)), roll_deg=float(np.rad2deg(roll)),
                              yaw_deg=float(np.rad2deg(yaw)))
        scene.view = "protocol"
        return
    raise RuntimeError(f"scene {scene.seed}: no camera position as instructed found")


def _look_up(scene: Scene, rng: np.random.Generator) -> None:
    """Move the camera 1-5 m from the main tree, 1.3-1.8 m above the ground, and aim it up the
    trunk at a point 2 m high to 2 m above the crown's base (at most 10 m), 30-70 degrees up,
    rolled up to 8 degrees (in place). Positions within 0.6 m of another stem are skipped."""
    main = scene.trees[0]
    cam = scene.camera
    W, H, K = cam.width, cam.height, cam.K
    others = scene.trees[1:]
    for _attempt in range(50):
        d = float(rng.uniform(1.0, 5.0)) + main.r_bh
        az = rng.uniform(0, 2 * np.pi)
        xy = main.base[:2] + d * np.array([np.cos(az), np.sin(az)])
        if any(np.hypot(*(t.base[:2] - xy)) < t.r_bh + 0.6 for t in others):
            continue
        h = float(rng.uniform(1.3, 1.8))
        pos = np.array([xy[0], xy[1], float(ground_height(scene.ground, *xy)) + h])
        top = max(2.5, min(10.0, main.height_m - 1.0, main.crown_base_m + 2.0))
        target = main.axis_point(rng.uniform(2.0, top))
        rel = target - pos
        pitch = float(np.clip(np.arctan2(rel[2], np.hypot(rel[0], rel[1])) + rng.normal(0, 0.1),
                              np.deg2rad(30), np.deg2rad(70)))
        yaw = np.arctan2(rel[1], rel[0]) + np.arctan((rng.uniform(0.3, 0.7) - 0.5) * W / K[0, 0])
        roll = np.deg2rad(rng.uniform(-8, 8))
        Rwc = _rotation(yaw, pitch, roll)
        pc = Rwc.T @ (target - pos)
        if pc[2] <= 0.5:
            continue
        u = K[0, 0] * pc[0] / pc[2] + K[0, 2]
        v = K[1, 1] * pc[1] / pc[2] + K[1, 2]
        if 0.1 * W < u < 0.9 * W and 0.1 * H < v < 0.9 * H:
            scene.camera = Camera(width=W, height=H, K=K, dist=cam.dist, R_wc=Rwc, t_wc=pos, height_m=h,
                                  pitch_deg=float(np.rad2deg(pitch)), roll_deg=float(np.rad2deg(roll)),
                                  yaw_deg=float(np.rad2deg(yaw)))
            scene.view = "upward"
            return


def _foot_hidden(scene: Scene, rng: np.random.Generator) -> None:
    """Grass tufts round the main stem's foot (1-3 patches 0.4-1.5 m across, 0.05-0.6 m high)
    and, with probability 0.35, a bush (radius 0.25-0.6 m) 0.2-1.0 m in front of the foot on the
    camera's side, within 0.3 m of the line of sight (in place)."""
    base = _foot_tufts(scene, rng, (0.05, 0.6))
    if rng.random() < 0.35:
        to_cam = np.asarray(scene.camera.t_wc[:2], np.float64) - base[:2]
        to_cam /= np.linalg.norm(to_cam) + 1e-12
        side = np.array([-to_cam[1], to_cam[0]])
        c = base[:2] + rng.uniform(0.2, 1.0) * to_cam + rng.uniform(-0.3, 0.3) * side
        _foot_bush(scene, rng, c, (0.25, 0.6))


def _foot_clutter(scene: Scene, rng: np.random.Generator) -> None:
    """Grass tufts round the main stem's foot (1-3 patches 0.4-1.5 m across, 0.08-0.35 m high)
    and, with probability 0.4, a low bush (radius 0.2-0.55 m) 0.3-1.0 m from it (in place)."""
    base = _foot_tufts(scene, rng, (0.08, 0.35))
    if rng.random() < 0.4:
        a = rng.uniform(0, 2 * np.pi)
        c = base[:2] + rng.uniform(0.3, 1.0) * np.array([np.cos(a), np.sin(a)])
        _foot_bush(scene, rng, c, (0.2, 0.55))


def _foot_tufts(scene: Scene, rng: np.random.Generator, height_m: tuple[float, float]) -> np.ndarray:
    """1-3 grass patches 0.4-1.5 m across, ``height_m`` (low, high) tall, round the main stem's
    foot (in place); returns that foot (3,)."""
    base = scene.trees[0].base
    for _ in range(int(rng.integers(1, 4))):
        c = base[:2] + rng.normal(0, 0.3, 2)
        scene.grass.append((c, float(rng.uniform(0.4, 1.5)), float(rng.uniform(150, 450)),
                            float(rng.uniform(*height_m))))
    return base


def _foot_bush(scene: Scene, rng: np.random.Generator, c: np.ndarray, radius_m: tuple[float, float]) -> None:
    """A green bush of radius in ``radius_m`` standing on the ground at ``c`` (2,) (in place)."""
    r = float(rng.uniform(*radius_m))
    zc = float(ground_height(scene.ground, *c)) + r * 0.5
    rgb = (rng.uniform(0.03, 0.1), rng.uniform(0.1, 0.22), rng.uniform(0.02, 0.05))
    scene.bushes.append((np.array([c[0], c[1], zc]), r, rgb, False))


def _open_grown(t: Tree, rng, scale: float = 1.0) -> None:
    """Make ``t`` an open-grown tree: a low, wide, dense crown (in place)."""
    t.height_m = float(rng.uniform(9.0, 24.0) * scale)
    t.crown_base_m = float(rng.uniform(2.2, 5.5))
    t.crown_radius_m = float(np.clip(t.r_bh * 2 * rng.uniform(10, 22), 2.5, 9.0) * scale)
    t.crown_density = float(rng.uniform(4.0, 10.0))
    t.leaf_scale = float(rng.uniform(1.3, 2.2))
    t.dead = False
    if rng.random() < 0.5:                               # dark summer green
        t.leaf_rgb = tuple(np.array([rng.uniform(0.04, 0.20), rng.uniform(0.12, 0.30), rng.uniform(0.01, 0.06)]))
    else:                                                # light, yellowish spring or sunlit green
        g = rng.uniform(0.15, 0.45)
        t.leaf_rgb = (g * rng.uniform(0.3, 0.8), g, g * rng.uniform(0.05, 0.25))
    nb = int(rng.integers(4, 10))
    t.branches = [(float(rng.uniform(t.crown_base_m * 0.8, t.crown_base_m + 0.5 * (t.height_m - t.crown_base_m))),
                   float(rng.uniform(0, 2 * np.pi)), float(np.deg2rad(rng.uniform(5, 55))),
                   float(rng.uniform(0.4, 0.9) * t.crown_radius_m), float(max(0.02, rng.uniform(0.25, 0.5) * t.r_bh)))
                  for _ in range(nb)]


def _to_park(scene: Scene, rng) -> None:
    """Turn a sampled forest scene into a park scene, in place: the main tree open-grown, a few
    other open-grown trees far apart, a distant tree line, a lawn, and the camera stepped back
    3-25 m and aimed so that the foot and much of the crown are in view. Draws only from ``rng``.
    """
    main = scene.trees[0]
    if rng.random() < 0.7:                               # park trees are mostly big
        k = float(rng.uniform(1.0, 2.2))
        main.r_bh = float(min(main.r_bh * k, 0.5))
        main._perimeter_cache = {}
    main.species = str(rng.choice(["beech", "oak", "maple", "oak", "maple", "birch", "pine"]))
    _open_grown(main, rng)
    main.lod = 0
    cam = scene.camera
    dist_h = float(np.exp(rng.uniform(np.log(3.0), np.log(25.0))))
    cam_az = rng.uniform(0, 2 * np.pi)
    cam_xy = main.base[:2] + dist_h * np.array([np.cos(cam_az), np.sin(cam_az)])
    cam_h = float(rng.uniform(1.2, 1.8))
    cam_pos = np.array([cam_xy[0], cam_xy[1], float(ground_height(scene.ground, *cam_xy)) + cam_h])
    # other trees: a few, far from the main one; a tree line beyond it
    keep = [main]
    others = [t for t in scene.trees[1:] if t.r_bh > 0.04]
    rng.shuffle(others)
    for t in others[:int(rng.integers(0, 7))]:
        ang = rng.uniform(0, 2 * np.pi)
        xy = main.base[:2] + rng.uniform(9.0, 35.0) * np.array([np.cos(ang), np.sin(ang)])
        if np.hypot(*(xy - cam_xy)) < 4.0:
            continue
        _place(t, xy, scene.ground)
        _open_grown(t, rng, scale=float(rng.uniform(0.6, 1.1)))
        keep.append(t)
    if rng.random() < 0.8:
        back = main.base[:2] - cam_xy
        back = back / np.linalg.norm(back)
        side = np.array([-back[1], back[0]])
        d_line = float(rng.uniform(30.0, 60.0))
        for t in others[7:7 + int(rng.integers(6, 16))]:
            xy = cam_xy + back * (dist_h + d_line + rng.normal(0, 4.0)) + side * rng.uniform(-45, 45)
            _place(t, xy, scene.ground)
            _open_grown(t, rng, scale=float(rng.uniform(0.7, 1.2)))
            keep.append(t)
    for i, t in enumerate(keep):
        t.id = i + 1
        if i:
            t.lod = 1 if np.hypot(*(t.base[:2] - cam_xy)) < 18 else 2
            t.rings = [r for r in t.rings if not r.is_rope]
            t.paint = None
    scene.trees = keep
    scene.distractors = [d for d in scene.distractors if d.get("kind") in ("red_leaves", "red_jacket")]
    scene.bushes = [b for b in scene.bushes if rng.random() < 0.4]
    scene.grass = []
    scene.logs = [] if rng.random() < 0.8 else scene.logs
    scene.ground["lawn"] = float(rng.uniform(0.6, 1.0))
    scene.stand = "park"
    # the camera: stepped back and aimed at the foot-to-crown span
    W, H = cam.width, cam.height
    K = cam.K
    f = K[0, 0]
    for _attempt in range(50):
        target = main.axis_point(rng.uniform(1.0, min(main.crown_base_m + 2.0, 6.0)))
        pitch = np.deg2rad(rng.uniform(-5, 28))
        roll = np.deg2rad(rng.uniform(-4, 4))
        rel = target - cam_pos
        yaw = np.arctan2(rel[1], rel[0]) + np.arctan((rng.uniform(0.2, 0.8) - 0.5) * W / f)
        Rwc = _rotation(yaw, pitch, roll)
        pts = np.stack([main.axis_point(BREAST_HEIGHT_M), target])
        pc = (pts - cam_pos) @ Rwc
        if np.any(pc[:, 2] <= 0.5):
            continue
        u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
        v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
        if np.all((0.08 * W < u) & (u < 0.92 * W) & (0.08 * H < v) & (v < 0.92 * H)):
            break
    scene.camera = Camera(width=W, height=H, K=K, dist=cam.dist, R_wc=Rwc, t_wc=cam_pos, height_m=cam_h,
                          pitch_deg=float(np.rad2deg(pitch)), roll_deg=float(np.rad2deg(roll)),
                          yaw_deg=float(np.rad2deg(yaw)))


def _place(t: Tree, xy, ground) -> None:
    """Move tree ``t``'s base to ground point ``xy`` (in place)."""
    t.base = np.array([xy[0], xy[1], float(ground_height(ground, xy[0], xy[1]))])


def _rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """World-from-camera rotation for a camera with heading ``yaw`` (about z, 0 = +x),
    ``pitch`` (positive looks up) and ``roll`` (positive turns the image clockwise).

    Returns (3, 3) with columns the camera's x (right), y (down), z (forward) in world.
    """
    f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    r0 = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    d0 = cross3(f, r0)                    # down = forward x right
    r = np.cos(roll) * r0 + np.sin(roll) * d0
    d = -np.sin(roll) * r0 + np.cos(roll) * d0
    return np.stack([r, d, f], axis=1)

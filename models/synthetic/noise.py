"""Tileable procedural noise textures (numpy only) used for bark, ground, sky and foliage.

Textures are small periodic float32 arrays sampled with wrap-around bilinear lookups, so a
scene costs a few milliseconds of texture synthesis whatever its resolution.
"""
from __future__ import annotations

import numpy as np

__all__ = ["fbm_texture", "sample_texture", "ridged"]


def _smooth_lattice(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Periodic value noise of ``cells`` x ``cells`` lattice upsampled to ``(size, size)``."""
    lat = rng.random((cells, cells), dtype=np.float32)
    t = np.arange(size, dtype=np.float32) * cells / size
    i0 = np.floor(t).astype(np.int64)
    f = t - i0
    f = f * f * (3 - 2 * f)
    i1 = (i0 + 1) % cells
    i0 = i0 % cells
    rows = lat[i0] * (1 - f)[:, None] + lat[i1] * f[:, None]
    out = rows[:, i0] * (1 - f)[None, :] + rows[:, i1] * f[None, :]
    return out


def fbm_texture(rng: np.random.Generator, size: int = 256, octaves: int = 5,
                base_cells: int = 4, gain: float = 0.5) -> np.ndarray:
    """Fractal (fBm) periodic noise in ``[0, 1]``.

    Parameters
    ----------
    rng : numpy.random.Generator
    size : int
        Side of the square texture; must be divisible by ``base_cells * 2**(octaves-1)``
        for perfect tiling (powers of two are).
    octaves, base_cells, gain : fBm parameters.

    Returns
    -------
    (size, size) float32 array in ``[0, 1]``.
    """
    acc = np.zeros((size, size), np.float32)
    amp, norm, cells = 1.0, 0.0, base_cells
    for _ in range(octaves):
        acc += amp * _smooth_lattice(rng, size, min(cells, size))
        norm += amp
        amp *= gain
        cells *= 2
    acc /= norm
    lo, hi = acc.min(), acc.max()
    return ((acc - lo) / max(hi - lo, 1e-6)).astype(np.float32)


def ridged(tex: np.ndarray) -> np.ndarray:
    """Ridged transform ``1 - |2t - 1|`` giving crest lines (bark ridges, furrows)."""
    return (1.0 - np.abs(2.0 * tex - 1.0)).astype(np.float32)


def sample_texture(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear wrap-around lookup.

    Parameters
    ----------
    tex : (S, S) or (S, S, C) array
    u, v : (N,) arrays of texture coordinates in texture periods (1.0 = one tile).

    Returns
    -------
    (N,) or (N, C) float32 array.
    """
    s0, s1 = tex.shape[:2]
    x = (np.asarray(u, np.float64) % 1.0) * s1
    y = (np.asarray(v, np.float64) % 1.0) * s0
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = (x - x0).astype(np.float32)
    fy = (y - y0).astype(np.float32)
    x0 %= s1
    y0 %= s0
    x1 = (x0 + 1) % s1
    y1 = (y0 + 1) % s0
    if tex.ndim == 3:
        fx = fx[:, None]
        fy = fy[:, None]
    a = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    b = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return (a * (1 - fy) + b * fy).astype(np.float32)

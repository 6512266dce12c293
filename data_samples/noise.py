"""Procedural value noise, evaluated at arbitrary world points (vectorised)."""

from __future__ import annotations

import numpy as np

_M = np.uint64(0xFFFFFFFFFFFFFFFF)


def _hash01(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    with np.errstate(over="ignore"):  # wrap-around multiplication is the hash
        return _hash01_wrapping(ix, iy, seed)


def _hash01_wrapping(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    h = (ix.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) ^ (
        iy.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
    )
    h ^= np.uint64(seed * 0x165667B19E3779F9 & 0xFFFFFFFFFFFFFFFF)
    h ^= h >> np.uint64(33)
    h = (h * np.uint64(0xFF51AFD7ED558CCD)) & _M
    h ^= h >> np.uint64(33)
    h = (h * np.uint64(0xC4CEB9FE1A85EC53)) & _M
    h ^= h >> np.uint64(33)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def value_noise(x: np.ndarray, y: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """Smooth noise in [0, 1) with features of about ``scale`` metres."""
    xs, ys = np.asarray(x) / scale, np.asarray(y) / scale
    x0, y0 = np.floor(xs), np.floor(ys)
    fx, fy = xs - x0, ys - y0
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    ix, iy = x0.astype(np.int64), y0.astype(np.int64)
    v00 = _hash01(ix, iy, seed)
    v10 = _hash01(ix + 1, iy, seed)
    v01 = _hash01(ix, iy + 1, seed)
    v11 = _hash01(ix + 1, iy + 1, seed)
    return (v00 * (1 - fx) + v10 * fx) * (1 - fy) + (v01 * (1 - fx) + v11 * fx) * fy


def fbm(x: np.ndarray, y: np.ndarray, scale: float, seed: int, octaves: int = 4) -> np.ndarray:
    """Fractal sum of value noise in about [-1, 1], coarsest features ``scale`` metres."""
    total = np.zeros(np.broadcast(np.asarray(x), np.asarray(y)).shape)
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        total += amp * (value_noise(x, y, scale / 2**o, seed + 7919 * o) - 0.5)
        norm += amp
        amp *= 0.5
    return 2.0 * total / norm

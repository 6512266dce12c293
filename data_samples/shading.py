"""Albedo of the procedural materials and Lambertian shading under the sun.

Albedos are linear reflectances in [0, 1]; images are tone-mapped with a 2.2
gamma. All textures are functions of world coordinates, so every view of a
point sees the same surface.
"""

from __future__ import annotations

import numpy as np

from .noise import fbm, value_noise
from .world import (
    K_ASPHALT,
    K_FACADE,
    K_GRASS,
    K_PAVEMENT,
    K_ROOF,
    K_RURAL,
    K_SOIL,
    K_TREE,
    K_TRUNK,
    World,
)

SKY_RGB = np.array([0.55, 0.65, 0.80])
AMBIENT = 0.35
SUN = 1.35


def albedo(world: World, tri: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Albedo (N, 3) of the hit triangles ``tri`` (N,) at world points ``P`` (N, 3)."""
    mat = world.material[tri]
    kind = world.mat_kind[mat]
    out = world.mat_rgb[mat].copy()
    x, y, z = P[:, 0], P[:, 1], P[:, 2]

    def sel(k):
        return np.nonzero(kind == k)[0]

    i = sel(K_ASPHALT)
    if i.size:
        xi, yi = x[i], y[i]
        out[i] *= (0.8 + 0.4 * value_noise(xi, yi, 0.2, 11) + 0.12 * fbm(xi, yi, 6.0, 12))[:, None]
        paint = _road_markings(world.roads, xi, yi)
        out[i] = np.where(paint[:, None], [0.55, 0.55, 0.52], out[i])
    i = sel(K_PAVEMENT)
    if i.size:
        gu, gv = np.mod(x[i] / 0.6, 1.0), np.mod(y[i] / 0.6, 1.0)
        joint = (gu < 0.06) | (gv < 0.06)
        f = (0.9 + 0.2 * value_noise(x[i], y[i], 0.3, 21)) * np.where(joint, 0.7, 1.0)
        out[i] *= f[:, None]
    i = sel(K_GRASS)
    if i.size:
        n1 = fbm(x[i], y[i], 4.0, 31)
        n2 = value_noise(x[i], y[i], 0.15, 32)
        out[i] *= (0.85 + 0.25 * n2 + 0.2 * n1)[:, None]
        out[i, 0] += 0.04 * np.clip(n1, 0, 1)  # drier, yellower patches
    i = sel(K_SOIL)
    if i.size:
        out[i] *= (0.8 + 0.3 * value_noise(x[i], y[i], 0.25, 41) + 0.2 * fbm(x[i], y[i], 3, 42))[
            :, None
        ]
    i = sel(K_RURAL)
    if i.size:
        field = value_noise(x[i], y[i], 45.0, 51)
        tones = np.array([[0.14, 0.20, 0.07], [0.28, 0.24, 0.12], [0.22, 0.18, 0.11]])
        out[i] = tones[np.minimum((field * 3).astype(int), 2)]
        out[i] *= (0.85 + 0.3 * value_noise(x[i], y[i], 0.5, 52))[:, None]
    i = sel(K_ROOF)
    if i.size:
        prm = world.mat_param[mat[i]]
        ax = world.axis[tri[i]]
        s = x[i] * ax[:, 0] + y[i] * ax[:, 1]
        stripes = (np.mod(s / prm[:, 1], 1.0) < 0.15) & (prm[:, 0] == 0)
        grain = 0.88 + 0.24 * value_noise(x[i], y[i], 0.15, 61) + 0.1 * fbm(x[i], y[i], 2.5, 62)
        out[i] *= (grain * np.where(stripes, 0.72, 1.0))[:, None]
    i = sel(K_FACADE)
    if i.size:
        prm = world.mat_param[mat[i]]
        ax = world.axis[tri[i]]
        u = x[i] * ax[:, 0] + y[i] * ax[:, 1]
        v = z[i] - prm[:, 3]
        period, win_w, floor_h = prm[:, 0], prm[:, 1], prm[:, 2]
        fu = np.abs(np.mod(u / period, 1.0) - 0.5) * period
        fv = np.mod(v, floor_h)
        window = (fu < win_w / 2) & (fv > 0.9) & (fv < 2.3) & (v > 0.8)
        frame = (fu < win_w / 2 + 0.08) & (fv > 0.82) & (fv < 2.38) & (v > 0.8) & ~window
        wall = out[i] * (0.92 + 0.16 * value_noise(x[i] + z[i], y[i] - z[i], 0.4, 71))[:, None]
        glass = np.array([0.05, 0.07, 0.09]) * (0.8 + 0.6 * value_noise(u, v, 3.0, 72))[:, None]
        out[i] = np.where(window[:, None], glass, np.where(frame[:, None], 0.75, wall))
    i = sel(K_TREE)
    if i.size:
        leaf = value_noise(x[i] + 0.7 * z[i], y[i] - 0.7 * z[i], 0.35, 81)
        out[i] *= (0.55 + 0.9 * leaf)[:, None]
    i = sel(K_TRUNK)
    if i.size:
        out[i] *= (0.8 + 0.4 * value_noise(x[i], z[i], 0.2, 91))[:, None]
    return np.clip(out, 0.0, 1.0)


def _road_markings(roads: list, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    paint = np.zeros(x.shape, bool)
    for r in roads:
        across, along = (x, y) if r["axis"] == "x" else (y, x)
        d = across - r["center"]
        centre = (np.abs(d) < 0.07) & (np.mod(along, 6.0) < 3.0)
        edge = np.abs(np.abs(d) - (r["width"] / 2 - 0.35)) < 0.07
        paint |= centre | edge
    return paint


def irradiance(normals: np.ndarray, sun: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """Light (N,) reaching surfaces with unit ``normals`` (N, 3): sky + sun if ``lit``."""
    sky = AMBIENT * (0.6 + 0.4 * normals[:, 2])
    return sky + SUN * np.clip(normals @ sun, 0.0, None) * lit


def tone_map(radiance: np.ndarray, gain=1.0) -> np.ndarray:
    """Linear radiance to 8-bit sRGB-like values (float, not yet rounded)."""
    return 255.0 * np.clip(radiance * gain, 0.0, 1.0) ** (1 / 2.2)

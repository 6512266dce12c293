"""Ray-cast rendering of the world with Open3D's RaycastingScene.

One primary ray per pixel centre, one shadow ray towards the sun per hit.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from workbench.camera import Camera
from workbench.raycast import Hits, cast, occluded

from .shading import SKY_RGB, albedo, irradiance, tone_map
from .world import World


def sun_lit(scene, hits: Hits, sun: np.ndarray) -> np.ndarray:
    """(N,) bool: the hit point sees the sun (a shadow ray per hit)."""
    lit = np.zeros(len(hits.t), bool)
    idx = np.nonzero(hits.tri >= 0)[0]
    idx = idx[hits.normals[idx] @ sun > 0]
    org = hits.points[idx] + 0.03 * hits.normals[idx]
    lit[idx] = ~occluded(scene, org, sun)
    return lit


def shade(world: World, scene, hits: Hits, sun: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear radiance (N, 3) of the hits (sky where nothing was hit) and the lit mask."""
    rad = np.tile(SKY_RGB, (len(hits.t), 1))
    hit = hits.tri >= 0
    lit = sun_lit(scene, hits, sun)
    if hit.any():
        alb = albedo(world, hits.tri[hit], hits.points[hit])
        rad[hit] = alb * irradiance(hits.normals[hit], sun, lit[hit])[:, None]
    return rad, lit


@dataclass
class Exposure:
    """Per-view photometric variation of a real camera."""

    gain: float = 1.0
    balance: tuple = (1.0, 1.0, 1.0)
    vignetting: float = 0.0  # relative fall-off at the image corner
    noise: float = 0.0  # read noise, 8-bit DN
    blur: float = 0.0  # optical PSF sigma, pixels


@dataclass
class ViewRender:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 true z-depth, NaN where nothing was hit
    lit: np.ndarray  # (H, W) bool
    tri: np.ndarray  # (H, W) int64


def render_view(world, scene, cam: Camera, sun, exposure: Exposure, rng) -> ViewRender:
    """Render a camera image and its true z-depth map."""
    H, W = cam.height, cam.width
    origin, dirs = cam.pixel_grid_rays()
    hits = cast(scene, origin, dirs)
    rad, lit = shade(world, scene, hits, sun)
    img = rad.reshape(H, W, 3)
    if exposure.blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), exposure.blur)
    if exposure.vignetting:
        v, u = np.mgrid[0:H, 0:W]
        r2 = ((u - W / 2) ** 2 + (v - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
        img = img * (1.0 - exposure.vignetting * r2)[..., None]
    img = img * np.asarray(exposure.balance)
    dn = tone_map(img, exposure.gain)
    if exposure.noise:
        shot = np.sqrt(np.maximum(dn, 0.0) / 255.0) * 2.0
        dn = dn + rng.normal(0.0, 1.0, dn.shape) * (exposure.noise + shot)
    rgb = np.clip(np.round(dn), 0, 255).astype(np.uint8)
    depth = np.where(np.isfinite(hits.t), hits.t, np.nan).astype(np.float32).reshape(H, W)
    return ViewRender(rgb, depth, lit.reshape(H, W), hits.tri.reshape(H, W))

"""The voxel paper's robustness experiment (Fig. 14): texture proxies that are wrong on
purpose, grown and shrunk by 10 % with noisy roof heights, and compare the seam cost of
the surface graph cuts with that of projective texture mapping in each case.

The scene's written poses carry its calibration error, so every case includes it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from workbench.meshes import concatenate_meshes
from workbench.raycast import raycasting_scene

from .building import Proxy, texture_building
from .options import VoxelOptions
from .proxy import VoxelFrame, proxy_mesh

PAPER_NOISE_M = 5.0  # +/- 5 m on the paper's buildings ...
PAPER_HEIGHT_M = 35.0  # ... whose default height is 35 m


def perturbed_mesh(
    proxy: Proxy, scale: float, height_noise_m: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """The proxy scaled about its grid's centre by ``scale`` in x and y, each roof plane
    moved up or down by a uniform draw in +/- ``height_noise_m`` (a flat roof kept at least
    one voxel up)."""
    f = proxy.frame
    nx, ny, _ = f.shape
    cx, cy = f.x0 + nx * f.r / 2, f.y0 + ny * f.r / 2
    frame = VoxelFrame(
        f.origin, f.axes, cx + (f.x0 - cx) * scale, cy + (f.y0 - cy) * scale, f.r * scale,
        f.shape, f.base_z,
    )  # fmt: skip
    planes = proxy.roof.planes.copy()
    # the same roof over the scaled grid: x = c + (x' - c) / scale
    planes[:, 3] += (planes[:, 0] * cx + planes[:, 1] * cy) * (1 - 1 / scale)
    planes[:, :2] /= scale
    planes /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    noise = rng.uniform(-height_noise_m, height_noise_m, len(planes))
    flat = (planes[:, 0] == 0) & (planes[:, 1] == 0)
    noise = np.where(flat, np.maximum(-planes[:, 3] + noise, f.r) + planes[:, 3], noise)
    planes[:, 3] -= planes[:, 2] * noise
    model = proxy_mesh(frame, replace(proxy.roof, planes=planes), 0.0)
    if model is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return model.mesh.vertices, model.mesh.triangles


def robustness_experiment(
    proxies: list[Proxy],
    cameras,
    images,
    options: VoxelOptions,
    change: float = 0.10,
    height_noise_m: float | None = None,
    seed: int = 0,
) -> dict:
    """Seam costs of graph cut and projective mapping on the proxies as built, grown by
    ``change`` and shrunk by ``change`` (with height noise).

    Parameters
    ----------
    height_noise_m : float, optional
        Default: the paper's +/- 5 m scaled by the median proxy height over 35 m.

    Returns
    -------
    dict: ``{"height_noise_m", "cases": {name: {"seam_cost", "seam_cost_projective",
    "ratio", "buildings"}}}``; costs are means over buildings.
    """
    tops = [p.model.ridge_z - p.frame.base_z for p in proxies if p.model is not None]
    if height_noise_m is None:
        height_noise_m = PAPER_NOISE_M * float(np.median(tops)) / PAPER_HEIGHT_M if tops else 0.0
    rng = np.random.default_rng(seed)
    cases = {
        "as built": (1.0, 0.0),
        f"grown {change:+.0%}": (1.0 + change, height_noise_m),
        f"shrunk {-change:+.0%}": (1.0 - change, height_noise_m),
    }
    out = {}
    for name, (scale, noise) in cases.items():
        meshes = [
            (p.vertices, p.triangles)
            if scale == 1.0 and noise == 0.0
            else perturbed_mesh(p, scale, noise, rng)
            for p in proxies
        ]
        V, T, _ = concatenate_meshes(meshes)
        occluders = raycasting_scene(V, T)
        cut, proj = [], []
        for p, (v, t) in zip(proxies, meshes, strict=True):
            if not len(t):
                continue
            rec = texture_building(p, cameras, images, options, occluders, v, t).record
            if np.isfinite(rec["seam_cost"]) and np.isfinite(rec["seam_cost_projective"]):
                cut.append(rec["seam_cost"])
                proj.append(rec["seam_cost_projective"])
        c, q = float(np.mean(cut)), float(np.mean(proj))
        out[name] = {
            "seam_cost": round(c, 4),
            "seam_cost_projective": round(q, 4),
            "ratio": round(c / q, 4) if q > 0 else None,
            "buildings": len(cut),
        }
    return {"height_noise_m": round(height_noise_m, 3), "cases": out}

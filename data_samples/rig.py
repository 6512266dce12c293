"""The flight: a grid of viewpoints, each with a nadir and four oblique cameras.

As in the voxel paper's data: one camera straight down and four tilted about 45
degrees towards north, east, south and west. The rig flies with a little roll,
pitch and yaw; the poses written to scene.json carry a calibration error.
"""

from __future__ import annotations

import numpy as np

from workbench.camera import Camera, look_at_rotation, rotation_about

DIRECTIONS = {"n": None, "N": (0.0, 1.0), "E": (1.0, 0.0), "S": (0.0, -1.0), "W": (-1.0, 0.0)}


def camera_rig(preset, ground_z: float, rng: np.random.Generator) -> list[tuple[str, Camera]]:
    """True cameras of the flight, named ``v{viewpoint:03d}_{n|N|E|S|W}``."""
    W, H = preset.image_size
    nx, ny = preset.grid
    cams = []
    for iy in range(ny):
        for ix in range(nx):
            vp = iy * nx + ix
            x = (ix - (nx - 1) / 2) * preset.spacing[0] + rng.uniform(-1.5, 1.5)
            y = (iy - (ny - 1) / 2) * preset.spacing[1] + rng.uniform(-1.5, 1.5)
            z = ground_z + preset.flying_height + rng.uniform(-1.0, 1.0)
            centre = np.array([x, y, z])
            jitter = np.radians(preset.attitude_jitter)
            rig = rotation_about(rng.normal(size=3), rng.uniform(0, jitter))
            for name, d in DIRECTIONS.items():
                if d is None:
                    forward, f = np.array([0.0, 0.0, -1.0]), preset.focal_px
                else:
                    tilt = np.radians(preset.oblique_tilt)
                    forward = np.array([np.sin(tilt) * d[0], np.sin(tilt) * d[1], -np.cos(tilt)])
                    f = preset.focal_px * preset.oblique_focal_scale
                # the rig's attitude turns every camera body with it
                R = look_at_rotation(forward) @ rig.T
                K = np.array([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
                cams.append((f"v{vp:03d}_{name}", Camera(K, R, -R @ centre, W, H)))
    return cams


def perturb_pose(cam: Camera, error_px: float, depth: float, rng, probe: np.ndarray) -> Camera:
    """The camera with a calibration error of ``error_px`` pixels RMS on ``probe`` points.

    Half of the error (in quadrature) comes from the attitude, half from the
    position, as a bundle adjustment's residual error would. The perturbation is
    scaled so that the RMS reprojection error over the probe points (N, 3) that the
    camera sees is exactly ``error_px``.
    """
    f = cam.K[0, 0]
    axis = rng.normal(size=3)
    shift = rng.normal(size=3)
    shift /= np.linalg.norm(shift)

    def moved(scale: float) -> Camera:
        R = rotation_about(axis, scale / np.sqrt(2) / f) @ cam.R
        centre = cam.center + shift * scale / np.sqrt(2) * depth / f
        return Camera(cam.K.copy(), R, -R @ centre, cam.width, cam.height, cam.distortion.copy())

    if error_px <= 0:
        return moved(0.0)
    rms = reprojection_rms(cam, moved(error_px), probe)
    if not np.isfinite(rms) or rms <= 0:
        return moved(error_px)
    return moved(error_px * error_px / rms)  # the error is linear in the scale


def reprojection_rms(true: Camera, written: Camera, points: np.ndarray) -> float:
    """RMS pixel distance between the projections of ``points`` by two cameras."""
    a, da = true.project(points)
    b, _ = written.project(points)
    ok = (da > 0) & np.all((a >= 0) & (a < [true.width, true.height]), axis=1)
    if not ok.any():
        return float("nan")
    return float(np.sqrt(np.mean(np.sum((a[ok] - b[ok]) ** 2, axis=1))))


def ground_margin(cams: list[Camera], ground_z: float, limit: float, half: float) -> float:
    """How far beyond the area of interest the views see ground (capped at ``limit``)."""
    reach = 0.0
    for cam in cams:
        corners = np.array(
            [[0, 0], [cam.width - 1, 0], [0, cam.height - 1], [cam.width - 1, cam.height - 1]],
            float,
        )
        origin, dirs = cam.pixel_rays(corners)
        down = dirs[:, 2] < -1e-6
        t = np.where(down, (ground_z - origin[2]) / np.where(down, dirs[:, 2], -1), np.inf)
        pts = origin[:2] + dirs[:, :2] * np.minimum(t, 1e6)[:, None]
        reach = max(reach, float(np.abs(pts).max()) - half)
    return float(np.clip(reach + 10.0, 20.0, limit))

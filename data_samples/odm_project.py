"""A scene written as an OpenDroneMap project, to test ``workbench import-odm`` against truth.

The views become OpenSfM shots in a topocentric frame around a reference latitude,
longitude and altitude (each camera moved out of the scene's CRS with pyproj: the inverse
of what the importer does), their intrinsics normalised by the larger image side (nadir
views as ``perspective`` cameras, the others as ``brown``), the images copied to
``images/``, and a DSM (the scene's truth, or any given) written as ``odm_dem/dsm.tif``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np

from workbench.odm import crs_to_topocentric, moved_pose
from workbench.raster import read_raster, write_raster
from workbench.scene import load_scene


def write_odm_project(scene_dir: Path, out: Path, reference: dict, dsm: Path | None = None) -> Path:
    """Write ``scene_dir`` as an ODM project in ``out``; returns ``out``.

    Parameters
    ----------
    reference : dict
        ``latitude``, ``longitude`` (degrees), ``altitude`` (metres) of the topocentric
        frame's origin.
    dsm : path, optional
        The DSM to write as ``odm_dem/dsm.tif`` (default: the scene's ``truth/dsm.tif``).
    """
    scene = load_scene(scene_dir)
    move = crs_to_topocentric(reference, scene.crs)
    (out / "images").mkdir(parents=True)
    (out / "opensfm").mkdir()
    (out / "odm_dem").mkdir()
    cameras, shots = {}, {}
    for view in scene.views:
        cam = view.camera
        name = Path(view.image_path).name
        shutil.copy2(view.image_path, out / "images" / name)
        s = max(cam.width, cam.height)
        K = cam.K
        nadir = cam.R[2, 2] < -0.95
        key = f"{'perspective' if nadir else 'brown'} {cam.width}x{cam.height} {K[0, 0]:.3f}"
        if nadir:
            cameras[key] = {
                "projection_type": "perspective", "width": cam.width, "height": cam.height,
                "focal": K[0, 0] / s, "k1": 0.0, "k2": 0.0,
            }  # fmt: skip
        else:
            cameras[key] = {
                "projection_type": "brown", "width": cam.width, "height": cam.height,
                "focal_x": K[0, 0] / s, "focal_y": K[1, 1] / s,
                "c_x": (K[0, 2] - (cam.width - 1) / 2) / s,
                "c_y": (K[1, 2] - (cam.height - 1) / 2) / s,
                "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0,
            }  # fmt: skip
        R, t = moved_pose(cam.R, cam.t, move)
        shots[name] = {
            "rotation": cv2.Rodrigues(R)[0].ravel().tolist(),
            "translation": t.tolist(),
            "camera": key,
        }
    doc = [{"cameras": cameras, "shots": shots, "points": {}, "reference_lla": reference}]
    (out / "opensfm" / "reconstruction.json").write_text(json.dumps(doc, indent=1))
    data, grid, crs = read_raster(dsm or scene.truth / "dsm.tif", as_float=True)
    write_raster(out / "odm_dem" / "dsm.tif", data.astype(np.float32), grid, crs)
    return out

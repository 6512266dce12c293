"""Import a COLMAP text model (cameras.txt, images.txt) as a workbench scene.

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); the workbench, like
OpenCV, at (0, 0): principal points are shifted by half a pixel on import.
COLMAP's pose (qvec, tvec) is world-to-camera, x_cam = R X + t, as ours.
Dense depth maps (``stereo/depth_maps/NAME.geometric.bin``) belong to the
undistorted images of a dense workspace: import ``dense/sparse`` with
``dense/images`` to use them.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np

from .atomic import atomic_output_dir
from .camera import Camera
from .errors import InputError
from .raster import parse_crs
from .scene import load_scene, write_scene_json

log = logging.getLogger(__name__)

# model name -> (number of parameters, function params -> (K entries, distortion))
_MODELS = {
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 4,
    "RADIAL": 5,
    "OPENCV": 8,
}


def _data_lines(path: Path) -> list[str]:
    if not path.exists():
        raise InputError(path, None, "file not found")
    return [ln.rstrip("\n") for ln in path.read_text().splitlines() if not ln.startswith("#")]


def read_cameras_txt(path: Path) -> dict[int, tuple[np.ndarray, np.ndarray, int, int]]:
    """COLMAP cameras.txt -> {camera_id: (K (3, 3) OpenCV convention, distortion (5,), w, h)}."""
    out = {}
    for n, line in enumerate(_data_lines(path)):
        parts = line.split()
        if not parts:
            continue
        where = f"line {n + 1} (camera {parts[0]})"
        if len(parts) < 4:
            raise InputError(path, where, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS")
        model = parts[1]
        if model not in _MODELS:
            raise InputError(
                path, where, f"unsupported camera model {model} (supported: {', '.join(_MODELS)})"
            )
        try:
            cam_id, w, h = int(parts[0]), int(parts[2]), int(parts[3])
            prm = [float(v) for v in parts[4:]]
        except ValueError:
            raise InputError(path, where, "non-numeric value") from None
        if len(prm) != _MODELS[model]:
            raise InputError(path, where, f"{model} takes {_MODELS[model]} parameters")
        dist = np.zeros(5)
        if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            fx = fy = prm[0]
            cx, cy = prm[1], prm[2]
            dist[: len(prm) - 3] = prm[3:]
        else:
            fx, fy, cx, cy = prm[:4]
            dist[:4] = prm[4:8] if model == "OPENCV" else 0.0
        K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
        out[cam_id] = (K, dist, w, h)
    return out


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """COLMAP/Hamilton quaternion (w, x, y, z) to a 3x3 rotation matrix."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def read_images_txt(path: Path) -> list[tuple[str, np.ndarray, np.ndarray, int]]:
    """COLMAP images.txt -> [(name, R (3, 3), t (3,), camera_id)], in file order."""
    lines = _data_lines(path)
    out = []
    # two lines per image; the second (2D points) may be empty
    for n in range(0, len(lines), 2):
        parts = lines[n].split()
        if not parts:
            continue
        where = f"image line {n // 2 + 1}"
        if len(parts) < 10:
            raise InputError(path, where, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        try:
            q = np.array([float(v) for v in parts[1:5]])
            t = np.array([float(v) for v in parts[5:8]])
            cam_id = int(parts[8])
        except ValueError:
            raise InputError(path, where, "non-numeric value") from None
        if not np.isfinite(q).all() or np.linalg.norm(q) < 1e-12:
            raise InputError(path, where, "invalid quaternion")
        out.append((" ".join(parts[9:]), quaternion_to_rotation(q), t, cam_id))
    return out


def read_colmap_depth(path: Path) -> np.ndarray:
    """A COLMAP dense depth map (.bin) as (H, W) float32 z-depth, NaN where unknown."""
    with open(path, "rb") as f:
        header = b""
        while header.count(b"&") < 3:
            c = f.read(1)
            if not c:
                raise InputError(path, None, "truncated COLMAP depth map header")
            header += c
        w, h, ch = (int(v) for v in header.split(b"&")[:3])
        data = np.fromfile(f, np.float32)
    if data.size != w * h * ch:
        raise InputError(path, None, f"expected {w}x{h}x{ch} values, found {data.size}")
    depth = data.reshape((w, h, ch), order="F").transpose(1, 0, 2)[..., 0]
    return np.where(depth > 0, depth, np.nan).astype(np.float32)


def import_colmap(
    model_dir: str | os.PathLike,
    images_dir: str | os.PathLike,
    out: str | os.PathLike,
    *,
    crs: str,
    depth_dir: str | os.PathLike | None = None,
    copy_images: bool = False,
    overwrite: bool = False,
) -> Path:
    """Convert a geo-registered COLMAP text model into a scene folder.

    Parameters
    ----------
    model_dir : path
        Folder with cameras.txt and images.txt, registered to a projected CRS
        with z up (for example with ``colmap model_aligner``).
    images_dir : path
        Folder holding the images named in images.txt.
    out : path
        The scene folder to write (atomically; validated before it appears).
    crs : str
        EPSG code or WKT of the model's frame.
    depth_dir : path, optional
        COLMAP ``stereo/depth_maps`` folder; ``NAME.geometric.bin`` (or
        ``.photometric.bin``) becomes the view's depth map.
    copy_images : bool
        Copy the images into the scene instead of referring to them.
    overwrite : bool
        Replace ``out`` if it exists.

    Returns
    -------
    Path of the written scene.json.
    """
    model_dir, images_dir = Path(model_dir), Path(images_dir)
    crs_obj = parse_crs(crs, path="--crs", field="crs")
    if not crs_obj.is_projected:
        raise InputError("--crs", "crs", "must be a projected CRS (metres)")
    cameras = read_cameras_txt(model_dir / "cameras.txt")
    images = read_images_txt(model_dir / "images.txt")
    if not images:
        raise InputError(model_dir / "images.txt", None, "no images")
    out = Path(out).absolute()
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        views = []
        for name, R, t, cam_id in images:
            if cam_id not in cameras:
                raise InputError(model_dir / "images.txt", name, f"unknown camera id {cam_id}")
            K, dist, w, h = cameras[cam_id]
            cam = Camera(K, R, t, w, h, dist)
            src = images_dir / name
            if not src.exists():
                raise InputError(src, None, f"image named in {model_dir / 'images.txt'} not found")
            if copy_images:
                dst = tmp / "images" / name
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dst)
                file = f"images/{name}"
            else:
                file = os.path.relpath(src.absolute(), out)
            view = {
                "id": Path(name).stem
                if len(images) == len({Path(n).stem for n, *_ in images})
                else name,
                "file": file,
                **cam.to_dict(),
            }
            if depth_dir is not None:
                dpath = _find_depth(Path(depth_dir), name)
                if dpath is not None:
                    depth = read_colmap_depth(dpath)
                    dst = tmp / "depth" / (Path(name).stem + ".npy")
                    dst.parent.mkdir(parents=True, exist_ok=True)
                    np.save(dst, depth)
                    view["depth"] = f"depth/{dst.name}"
                else:
                    log.warning("%s: no depth map in %s", name, depth_dir)
            views.append(view)
        if np.mean([v["R"][2][2] for v in views]) > 0:
            log.warning("cameras look upwards on average: is the model registered with z up?")
        write_scene_json(tmp, crs=crs_obj, views=views)
        load_scene(tmp)  # validate before the scene appears
    return out / "scene.json"


def _find_depth(depth_dir: Path, name: str) -> Path | None:
    for suffix in (".geometric.bin", ".photometric.bin"):
        p = depth_dir / (name + suffix)
        if p.exists():
            return p
    return None

"""Import an OpenDroneMap (OpenSfM) project as a workbench scene: ``workbench import-odm``.

OpenSfM writes its reconstruction in a topocentric frame (east, north, up) around a
reference latitude, longitude and altitude (WGS84), with cameras x_cam = R X + t (R from
an axis-angle ``rotation``) and focal lengths and principal points normalised by the
larger image side, the centre of the image at 0. ODM adds the DSM (``odm_dem/dsm.tif``)
and optionally the DTM and the georeferenced cloud, in a projected CRS (UTM).

Each camera centre is moved into the scene's projected CRS with pyproj; its orientation
follows the local axes of that CRS at the camera (the Jacobian of the transformation there,
made a rotation), so the meridian convergence of UTM (about a degree at 4 degrees from the
central meridian) is carried into R. Perspective and Brown cameras map to OpenCV pinhole
cameras with distortion; fisheye images are resampled to pinhole images.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import cv2
import numpy as np
from rasterio.crs import CRS

from .atomic import atomic_output_dir
from .camera import Camera
from .errors import InputError
from .raster import parse_crs, read_raster
from .scene import load_scene, write_scene_json

log = logging.getLogger(__name__)

MODELS = ("perspective", "simple_radial", "radial", "brown", "fisheye")
WGS84_3D = "EPSG:4979"  # longitude, latitude, ellipsoidal height


def topocentric_to_crs(reference: dict, crs: CRS):
    """A function (N, 3) topocentric ENU metres -> (N, 3) easting, northing, height in
    ``crs`` (ellipsoidal height), through WGS84 (pyproj)."""
    from pyproj import Transformer

    lat, lon, alt = (float(reference[k]) for k in ("latitude", "longitude", "altitude"))
    to_geodetic = Transformer.from_pipeline(
        "+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 "
        f"+lat_0={lat} +lon_0={lon} +h_0={alt} +step +inv +proj=cart +ellps=WGS84 "
        "+step +proj=unitconvert +xy_in=rad +xy_out=deg"
    )
    to_crs = Transformer.from_crs(WGS84_3D, crs.to_wkt(), always_xy=True)

    def move(points: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(np.asarray(points, np.float64))
        lon_, lat_, h = to_geodetic.transform(p[:, 0], p[:, 1], p[:, 2])
        x, y, z = to_crs.transform(lon_, lat_, h)
        return np.column_stack([x, y, z])

    return move


def crs_to_topocentric(reference: dict, crs: CRS):
    """The inverse of :func:`topocentric_to_crs`."""
    from pyproj import Transformer

    lat, lon, alt = (float(reference[k]) for k in ("latitude", "longitude", "altitude"))
    to_geodetic = Transformer.from_crs(crs.to_wkt(), WGS84_3D, always_xy=True)
    to_enu = Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
        "+step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lat_0={lat} +lon_0={lon} +h_0={alt}"
    )

    def move(points: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(np.asarray(points, np.float64))
        lon_, lat_, h = to_geodetic.transform(p[:, 0], p[:, 1], p[:, 2])
        return np.column_stack(to_enu.transform(lon_, lat_, h))

    return move


def moved_pose(R: np.ndarray, t: np.ndarray, move) -> tuple[np.ndarray, np.ndarray]:
    """The pose x_cam = R X + t of a camera in the source frame, in the frame ``move``
    maps to: the centre moved exactly, the axes by the map's Jacobian at the centre made a
    rotation (its polar factor)."""
    C = -R.T @ t
    h = 1.0  # metres: the map is smooth over far more than this
    J = np.column_stack([(move(C + h * e)[0] - move(C - h * e)[0]) / (2 * h) for e in np.eye(3)])
    U, _, Vt = np.linalg.svd(J)
    Q = U @ Vt  # the rotation nearest to J
    C2 = move(C)[0]
    R2 = R @ Q.T
    return R2, -R2 @ C2


def opensfm_camera(params: dict, width: int, height: int, where: str, path: Path):
    """OpenCV K (3, 3) and distortion (5,) of an OpenSfM camera for an image of
    ``width`` x ``height`` pixels (it may have been resized since), and whether it is a
    fisheye (equidistant) camera whose images must be resampled."""
    kind = params.get("projection_type")
    if kind not in MODELS:
        raise InputError(
            path, f"{where}.projection_type",
            f"camera model {kind!r} is not supported (supported: {', '.join(MODELS)})",
        )  # fmt: skip
    s = max(width, height)
    try:
        if "focal_x" in params:  # brown, simple_radial, radial: focal and centre per axis
            fx, fy = float(params["focal_x"]) * s, float(params["focal_y"]) * s
            cx = (width - 1) / 2 + float(params.get("c_x", 0.0)) * s
            cy = (height - 1) / 2 + float(params.get("c_y", 0.0)) * s
        else:  # perspective, fisheye: one focal, the image centre
            fx = fy = float(params["focal"]) * s
            cx, cy = (width - 1) / 2, (height - 1) / 2
        # OpenSfM's radial and Brown terms are OpenCV's; a model without one has it 0
        dist = [float(params.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")]
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(path, where, f"camera parameter missing or not a number ({exc})") from None
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return K, np.array(dist, np.float64), kind == "fisheye"


def _reconstruction(project: Path) -> tuple[dict, dict, Path]:
    path = project / "opensfm" / "reconstruction.json"
    if not path.exists():
        raise InputError(path, None, "not found: is this an ODM project (with opensfm/)?")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"not valid JSON ({exc})") from None
    if not isinstance(doc, list) or not doc or not all(isinstance(r, dict) for r in doc):
        raise InputError(path, None, "expected a list of reconstructions")
    rec = max(doc, key=lambda r: len(r.get("shots", {})))
    if len(doc) > 1:
        log.warning("%s: %d reconstructions; the largest (%d shots) is imported",
                    path, len(doc), len(rec.get("shots", {})))  # fmt: skip
    reference = rec.get("reference_lla")
    ref_path = project / "opensfm" / "reference_lla.json"
    if reference is None and ref_path.exists():
        reference = json.loads(ref_path.read_text())
    if not isinstance(reference, dict) or not {"latitude", "longitude", "altitude"} <= set(
        reference
    ):
        raise InputError(path, "reference_lla", "no reference latitude, longitude, altitude")
    if not rec.get("shots"):
        raise InputError(path, "shots", "the reconstruction has no shots")
    return rec, reference, path


def _first(project: Path, *names: str) -> Path | None:
    return next((project / n for n in names if (project / n).exists()), None)


def import_odm(
    project: str | os.PathLike,
    out: str | os.PathLike,
    *,
    crs: str | None = None,
    training_labels: str | os.PathLike | None = None,
    copy_images: bool = False,
    overwrite: bool = False,
) -> Path:
    """Convert an ODM project folder into a scene folder.

    Parameters
    ----------
    project : path
        The ODM project: ``opensfm/reconstruction.json``, ``images/``, ``odm_dem/dsm.tif``
        and, when present, ``odm_dem/dtm.tif`` and ``odm_georeferencing/
        odm_georeferenced_model.laz``.
    out : path
        The scene folder (written atomically, validated before it appears).
    crs : str, optional
        The scene's projected CRS; by default the DSM's.
    training_labels : path, optional
        Strokes (a label raster) for the fusion's per-view forest.
    copy_images : bool
        Copy the images (always done for fisheye images, which are resampled).

    Returns
    -------
    Path of the written scene.json.
    """
    project, out = Path(project).absolute(), Path(out).absolute()
    if not project.is_dir():
        raise InputError(project, None, "ODM project folder not found")
    rec, reference, rec_path = _reconstruction(project)
    dsm = project / "odm_dem" / "dsm.tif"
    if not dsm.exists():
        raise InputError(dsm, None, "the ODM project has no DSM (run ODM with --dsm)")
    _, dsm_grid, dsm_crs = read_raster(dsm, field="dsm")
    target = parse_crs(crs, path="--crs", field="crs") if crs else dsm_crs
    if target is None or not target.is_projected:
        raise InputError(dsm if not crs else "--crs", "crs", "a projected CRS is needed")
    if dsm_crs is not None and dsm_crs != target:
        raise InputError(dsm, "crs", "differs from --crs; reproject the DSM or omit --crs")
    move = topocentric_to_crs(reference, target)
    dtm = _first(project, "odm_dem/dtm.tif")
    points = _first(
        project, "odm_georeferencing/odm_georeferenced_model.laz", "odm_georeferenced_model.laz"
    )
    cameras = rec.get("cameras", {})
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        views = []
        for name, shot in sorted(rec["shots"].items()):
            where = f"shots[{name!r}]"
            image = project / "images" / name
            if not image.exists():
                raise InputError(image, None, f"image of {where} in {rec_path} not found")
            params = cameras.get(shot.get("camera"))
            if params is None:
                raise InputError(
                    rec_path, f"{where}.camera", f"unknown camera {shot.get('camera')!r}"
                )
            pixels = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
            if pixels is None:
                raise InputError(image, None, "not a readable image")
            h, w = pixels.shape[:2]
            K, dist, fisheye = opensfm_camera(
                params, w, h, f"cameras[{shot['camera']!r}]", rec_path
            )
            try:
                R = cv2.Rodrigues(np.asarray(shot["rotation"], np.float64))[0]
                t = np.asarray(shot["translation"], np.float64).reshape(3)
            except (KeyError, ValueError, TypeError, cv2.error) as exc:
                raise InputError(
                    rec_path, where, f"rotation/translation unreadable ({exc})"
                ) from None
            R, t = moved_pose(R, t, move)
            if fisheye:
                pixels = cv2.fisheye.undistortImage(pixels, K, dist[:4], Knew=K)
                dist = np.zeros(5)
            if fisheye or copy_images:
                dst = tmp / "images" / name
                dst.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(dst), pixels)
                file = f"images/{name}"
            else:
                file = os.path.relpath(image, out)
            views.append(
                {"id": Path(name).stem, "file": file, **Camera(K, R, t, w, h, dist).to_dict()}
            )
        rel = {k: os.path.relpath(v, out) if v is not None else None
               for k, v in (("dsm", dsm), ("dtm", dtm), ("points", points))}  # fmt: skip
        if training_labels is not None:
            rel["training_labels"] = os.path.relpath(Path(training_labels).absolute(), out)
        write_scene_json(
            tmp, crs=target, views=views, bounds=list(dsm_grid.bounds),
            source={"odm_project": str(project), "reference_lla": reference}, **rel,
        )  # fmt: skip
        load_scene(tmp)  # validate before the scene appears
    return out / "scene.json"

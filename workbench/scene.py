"""The scene: the workbench's input, a folder with ``scene.json``.

The schema is documented in README.md ("The scene format"). :func:`load_scene`
validates everything it can without reading pixels: matrix shapes, rotations,
image and depth-map sizes, the CRS, raster and GeoJSON files. Every problem is an
:class:`~workbench.errors.InputError` naming the file and the field.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rasterio.crs import CRS

from .camera import Camera
from .errors import InputError
from .imageio import image_size, read_rgb
from .raster import parse_crs

SCENE_FORMAT = "city-workbench-scene"
SCENE_VERSION = 1
DEPTH_SUFFIXES = (".npy", ".tif", ".tiff")
POINT_SUFFIXES = (".las", ".laz", ".ply")
ROTATION_TOLERANCE = 1e-5


@dataclass
class View:
    """One calibrated image of a scene.

    Attributes
    ----------
    id : str
        Unique name of the view.
    image_path : Path
        The image file (absolute).
    camera : Camera
        Its calibration.
    depth_path : Path or None
        Per-view z-depth map (float32 metres along the optical axis, NaN unknown).
    """

    id: str
    image_path: Path
    camera: Camera
    depth_path: Path | None = None

    def read_image(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB."""
        return read_rgb(self.image_path)

    def read_depth(self) -> np.ndarray:
        """(H, W) float32 z-depth in metres, NaN where unknown."""
        if self.depth_path is None:
            raise InputError(self.image_path, "depth", "view has no depth map")
        return read_depth(self.depth_path)


@dataclass
class Scene:
    """A validated scene.

    Attributes
    ----------
    root : Path
        The scene folder; relative paths in scene.json are relative to it.
    crs : rasterio.crs.CRS
        Projected CRS of the world frame (x east, y north, z up, metres).
    views : list of View
    bounds : (4,) tuple or None
        Area of interest (xmin, ymin, xmax, ymax), metres.
    gsd : float or None
        Reference ground sampling distance of the ortho products, metres.
    dsm, dtm, points, footprints, training_labels, truth : Path or None
        Optional inputs (absolute paths).
    """

    root: Path
    crs: CRS
    views: list[View]
    bounds: tuple[float, float, float, float] | None = None
    gsd: float | None = None
    dsm: Path | None = None
    dtm: Path | None = None
    points: Path | None = None
    footprints: Path | None = None
    training_labels: Path | None = None
    truth: Path | None = None
    extra: dict = field(default_factory=dict)

    @property
    def scene_json(self) -> Path:
        return self.root / "scene.json"


def read_depth(path: str | os.PathLike) -> np.ndarray:
    """Read a depth map (.npy or GeoTIFF/TIFF) as (H, W) float32, NaN where unknown."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        arr = np.load(path)
    else:
        import rasterio

        with rasterio.open(path) as src:
            arr = src.read(1)
            if src.nodata is not None and not np.isnan(src.nodata):
                arr = np.where(arr == src.nodata, np.nan, arr)
    return np.asarray(arr, dtype=np.float32)


def _depth_shape(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    if path.suffix.lower() == ".npy":
        arr = np.load(path, mmap_mode="r")
        return arr.shape, arr.dtype
    import rasterio

    with rasterio.open(path) as src:
        return (src.count, src.height, src.width), np.dtype(src.dtypes[0])


def _matrix(value, shape: tuple[int, ...], path: Path, where: str) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, where, f"expected a {shape} array of numbers") from None
    if arr.shape != shape:
        raise InputError(path, where, f"expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(path, where, "contains non-finite values")
    return arr


def _positive_int(value, path: Path, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise InputError(path, where, f"expected a positive integer, got {value!r}")
    return value


def parse_camera(entry: dict, path: Path, where: str) -> Camera:
    """Validate the camera fields of a view (K, R, t, width, height, distortion)."""
    for key in ("K", "R", "t", "width", "height"):
        if key not in entry:
            raise InputError(path, f"{where}.{key}", "missing")
    K = _matrix(entry["K"], (3, 3), path, f"{where}.K")
    if not np.allclose(K[2], [0, 0, 1], atol=1e-9) or abs(K[1, 0]) > 1e-9:
        raise InputError(path, f"{where}.K", "expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"{where}.K", "focal lengths must be positive")
    R = _matrix(entry["R"], (3, 3), path, f"{where}.R")
    ortho_err = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if ortho_err > ROTATION_TOLERANCE or det < 0:
        raise InputError(
            path,
            f"{where}.R",
            f"not a rotation matrix (max |R^T R - I| = {ortho_err:.2g}, det = {det:.4f})",
        )
    t = _matrix(entry["t"], (3,), path, f"{where}.t")
    width = _positive_int(entry["width"], path, f"{where}.width")
    height = _positive_int(entry["height"], path, f"{where}.height")
    dist = np.zeros(5)
    if entry.get("distortion") is not None:
        d = entry["distortion"]
        n = len(d) if isinstance(d, list) else -1
        if n not in (4, 5):
            raise InputError(path, f"{where}.distortion", "expected k1 k2 p1 p2 [k3]")
        dist[:n] = _matrix(d, (n,), path, f"{where}.distortion")
    return Camera(K=K, R=R, t=t, width=width, height=height, distortion=dist)


def _optional_file(doc: dict, key: str, root: Path, path: Path) -> Path | None:
    value = doc.get(key)
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise InputError(path, key, "expected a file path")
    p = (root / value).resolve()
    if not p.exists():
        raise InputError(path, key, f"file not found: {value}")
    return p


def load_scene(path: str | os.PathLike, *, check_files: bool = True) -> Scene:
    """Load and validate a scene.

    Parameters
    ----------
    path : path
        The scene folder or its ``scene.json``.
    check_files : bool
        Also open every referenced file to check image sizes, depth-map shapes,
        rasters and footprints (headers only; no pixels are decoded).

    Returns
    -------
    Scene

    Raises
    ------
    InputError
        Naming the file and the field of the first problem found.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "scene.json"
    if not path.exists():
        raise InputError(path, None, "scene file not found")
    root = path.parent.resolve()
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise InputError(path, None, "expected a JSON object")
    if doc.get("format", SCENE_FORMAT) != SCENE_FORMAT:
        raise InputError(path, "format", f"expected {SCENE_FORMAT!r}")
    if doc.get("version", SCENE_VERSION) != SCENE_VERSION:
        raise InputError(path, "version", f"unsupported version {doc.get('version')!r}")
    if "crs" not in doc:
        raise InputError(path, "crs", "missing (an EPSG code or WKT of a projected CRS)")
    crs = parse_crs(doc["crs"], path=path, field="crs")
    if not crs.is_projected:
        raise InputError(path, "crs", "must be a projected CRS (metres, z up), not geographic")

    bounds = doc.get("bounds")
    if bounds is not None:
        b = _matrix(bounds, (4,), path, "bounds")
        if not (b[2] > b[0] and b[3] > b[1]):
            raise InputError(path, "bounds", "expected [xmin, ymin, xmax, ymax] with min < max")
        bounds = tuple(float(v) for v in b)
    gsd = doc.get("gsd")
    if gsd is not None and (not isinstance(gsd, int | float) or gsd <= 0):
        raise InputError(path, "gsd", "expected a positive number of metres")

    images = doc.get("images", [])
    if not isinstance(images, list):
        raise InputError(path, "images", "expected a list")
    views, seen = [], set()
    for i, entry in enumerate(images):
        where = f"images[{i}]"
        if not isinstance(entry, dict):
            raise InputError(path, where, "expected an object")
        if not isinstance(entry.get("file"), str):
            raise InputError(path, f"{where}.file", "missing image file name")
        camera = parse_camera(entry, path, where)
        vid = str(entry.get("id", Path(entry["file"]).stem))
        if vid in seen:
            raise InputError(path, f"{where}.id", f"duplicate view id {vid!r}")
        seen.add(vid)
        image_path = (root / entry["file"]).resolve()
        depth_path = None
        if entry.get("depth") is not None:
            depth_path = (root / entry["depth"]).resolve()
            if depth_path.suffix.lower() not in DEPTH_SUFFIXES:
                raise InputError(path, f"{where}.depth", "expected a .npy or .tif depth map")
        if check_files:
            _check_view_files(path, where, image_path, depth_path, camera)
        views.append(View(vid, image_path, camera, depth_path))

    scene = Scene(
        root=root,
        crs=crs,
        views=views,
        bounds=bounds,
        gsd=float(gsd) if gsd is not None else None,
        dsm=_optional_file(doc, "dsm", root, path),
        dtm=_optional_file(doc, "dtm", root, path),
        points=_optional_file(doc, "points", root, path),
        footprints=_optional_file(doc, "footprints", root, path),
        training_labels=_optional_file(doc, "training_labels", root, path),
        truth=_optional_file(doc, "truth", root, path),
        extra={k: v for k, v in doc.items() if k not in _KNOWN_KEYS},
    )
    if scene.points is not None and scene.points.suffix.lower() not in POINT_SUFFIXES:
        raise InputError(path, "points", "expected a .las, .laz or .ply point cloud")
    if check_files:
        _check_optional_files(scene, path)
    return scene


_KNOWN_KEYS = {
    "format",
    "version",
    "crs",
    "bounds",
    "gsd",
    "images",
    "dsm",
    "dtm",
    "points",
    "footprints",
    "training_labels",
    "truth",
}


def _check_view_files(path, where, image_path, depth_path, camera: Camera) -> None:
    if not image_path.exists():
        raise InputError(path, f"{where}.file", f"image not found: {image_path}")
    try:
        w, h = image_size(image_path)
    except InputError as exc:
        raise InputError(path, f"{where}.file", exc.message) from None
    if (w, h) != (camera.width, camera.height):
        raise InputError(
            path,
            f"{where}.file",
            f"image is {w}x{h} but the camera says {camera.width}x{camera.height}",
        )
    if depth_path is None:
        return
    if not depth_path.exists():
        raise InputError(path, f"{where}.depth", f"depth map not found: {depth_path}")
    try:
        shape, dtype = _depth_shape(depth_path)
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file
        raise InputError(path, f"{where}.depth", f"unreadable depth map ({exc})") from None
    if len(shape) == 3 and shape[0] == 1:
        shape = shape[1:]
    if shape != (camera.height, camera.width):
        raise InputError(
            path,
            f"{where}.depth",
            f"depth map is {shape} but the image is ({camera.height}, {camera.width})",
        )
    if not np.issubdtype(dtype, np.floating):
        raise InputError(path, f"{where}.depth", f"expected float depths, got {dtype}")


def _check_optional_files(scene: Scene, path: Path) -> None:
    from .footprints import read_footprints
    from .raster import check_class_codes, read_raster

    for key in ("dsm", "dtm", "training_labels"):
        p = getattr(scene, key)
        if p is None:
            continue
        try:
            data, _, crs = read_raster(p)
        except InputError as exc:
            raise InputError(path, key, f"{p.name}: {exc.message}") from None
        if data.shape[0] != 1:
            raise InputError(path, key, f"{p.name}: expected one band, got {data.shape[0]}")
        if crs is not None and crs != scene.crs:
            raise InputError(path, key, f"{p.name}: CRS differs from the scene's")
        if key == "training_labels":
            check_class_codes(data, p, key)
    if scene.footprints is not None:
        read_footprints(scene.footprints, crs=scene.crs, extent=scene.bounds)


def write_scene_json(
    folder: str | os.PathLike,
    *,
    crs: CRS,
    views: list[dict],
    **optional,
) -> Path:
    """Write ``scene.json`` into ``folder``.

    Parameters
    ----------
    folder : path
        The scene folder.
    crs : CRS
        Projected CRS; written as ``EPSG:n`` when it has one, WKT otherwise.
    views : list of dict
        Each with ``id``, ``file``, the camera fields (see :meth:`Camera.to_dict`) and
        optionally ``depth``; paths relative to ``folder``.
    **optional
        ``bounds``, ``gsd``, ``dsm``, ``dtm``, ``points``, ``footprints``,
        ``training_labels``, ``truth`` and any extra keys; None values are left out.
    """
    epsg = crs.to_epsg()
    doc = {
        "format": SCENE_FORMAT,
        "version": SCENE_VERSION,
        "crs": f"EPSG:{epsg}" if epsg else crs.to_wkt(),
    }
    doc.update({k: v for k, v in optional.items() if v is not None})
    doc["images"] = views
    out = Path(folder) / "scene.json"
    out.write_text(json.dumps(doc, indent=1) + "\n")
    return out

"""Reading point clouds: LAS/LAZ tiles (laspy) and PLY (Open3D), one or many, into one cloud.

A survey comes as tiles. ``read_clouds`` takes files and folders, reads every tile's CRS
with laspy's own parser (GeoTIFF keys or WKT, in VLRs or EVLRs), refuses tiles whose CRSs
differ, and merges them: the same returns as one file holding them all.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rasterio.crs import CRS

from workbench.errors import InputError
from workbench.raster import crs_name, parse_crs

CLOUD_SUFFIXES = (".las", ".laz", ".ply")


@dataclass
class PointCloud:
    """Points and what they carry; xyz in the CRS's units."""

    xyz: np.ndarray  # (N, 3) float64
    rgb: np.ndarray | None  # (N, 3) uint8
    intensity: np.ndarray | None  # (N,) float
    classification: np.ndarray | None  # (N,) uint8, ASPRS codes
    crs: CRS | None
    source: str
    number_of_returns: np.ndarray | None = None  # (N,) uint8
    return_number: np.ndarray | None = None  # (N,) uint8


def las_crs(las, path) -> CRS | None:
    """The CRS a LAS/LAZ header declares (laspy's parser: WKT or GeoTIFF keys, VLRs and
    EVLRs), or None."""
    try:
        found = las.header.parse_crs(prefer_wkt=True)
    except Exception as exc:  # noqa: BLE001 - pyproj and laspy raise many types
        raise InputError(path, "crs", f"the header's CRS cannot be read ({exc})") from None
    if found is None:
        return None
    return parse_crs(found.to_wkt(), path=path, field="crs")


def read_points(path: str | os.PathLike, crs: str | None = None) -> PointCloud:
    """Read one LAS, LAZ or PLY cloud.

    Parameters
    ----------
    path : path
    crs : str, optional
        EPSG code or WKT for a cloud that carries none (overrides nothing else).

    Raises
    ------
    InputError
        Missing, corrupt or empty file, unknown CRS, a LAS file with no CRS and no ``crs``.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, None, "point cloud not found")
    suffix = path.suffix.lower()
    given = parse_crs(crs, path="--crs", field="crs") if crs else None
    if suffix in (".las", ".laz"):
        import laspy

        try:
            las = laspy.read(path)
        except Exception as exc:  # noqa: BLE001 - laspy raises many types for bad files
            raise InputError(path, None, f"not a readable LAS/LAZ file ({exc})") from None
        if len(las.points) == 0:
            raise InputError(path, "point_count", "the tile has no points")
        xyz = np.column_stack([las.x, las.y, las.z]).astype(np.float64)
        names = set(las.point_format.dimension_names)
        rgb = None
        if {"red", "green", "blue"} <= names:
            rgb16 = np.column_stack([las.red, las.green, las.blue]).astype(np.float64)
            scale = 257.0 if rgb16.max() > 255 else 1.0
            rgb = np.clip(np.round(rgb16 / scale), 0, 255).astype(np.uint8)
        intensity = np.asarray(las.intensity, np.float64) if "intensity" in names else None
        cls = np.asarray(las.classification, np.uint8) if "classification" in names else None
        file_crs = las_crs(las, path)
        if file_crs is None and given is None:
            raise InputError(path, "crs", "the file names no CRS; pass --crs")
        echoes = {
            k: np.asarray(las[k], np.uint8) if k in names else None
            for k in ("number_of_returns", "return_number")
        }
        return PointCloud(xyz, rgb, intensity, cls, given or file_crs, str(path), **echoes)
    if suffix == ".ply":
        import open3d as o3d

        pc = o3d.io.read_point_cloud(str(path))
        if len(pc.points) == 0:
            raise InputError(path, None, "no points (or not a readable PLY file)")
        rgb = (np.asarray(pc.colors) * 255).round().astype(np.uint8) if pc.has_colors() else None
        return PointCloud(np.asarray(pc.points, np.float64), rgb, None, None, given, str(path))
    raise InputError(path, None, "expected a .las, .laz or .ply point cloud")


def cloud_files(paths) -> list[Path]:
    """The cloud files named: each file as given, each folder's .las/.laz/.ply files sorted.

    Raises
    ------
    InputError
        A folder with no cloud in it.
    """
    files = []
    for p in map(Path, [paths] if isinstance(paths, str | os.PathLike) else paths):
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.suffix.lower() in CLOUD_SUFFIXES)
            if not found:
                raise InputError(p, None, "no .las, .laz or .ply file in the folder")
            files += found
        else:
            files.append(p)
    return files


def check_same_crs(cloud: PointCloud, first: PointCloud) -> None:
    """Refuse a tile whose CRS is not the survey's first tile's, naming both."""
    a, b = cloud.crs, first.crs
    if (a is None) != (b is None) or (a is not None and a != b):
        raise InputError(cloud.source, "crs", f"{crs_name(a)} differs from {crs_name(b)} of "
                         f"{first.source}; reproject the tiles to one CRS")  # fmt: skip


def read_clouds(paths, crs: str | None = None) -> PointCloud:
    """Read and merge point-cloud tiles (files or folders of them) into one cloud.

    Attributes kept are those every tile has (colour, intensity, classes, echoes).

    Raises
    ------
    InputError
        An unreadable or empty tile, or tiles whose CRSs differ (naming both).
    """
    files = cloud_files(paths)
    clouds = [read_points(f, crs) for f in files]
    first = clouds[0]
    for c in clouds[1:]:
        check_same_crs(c, first)
    if len(clouds) == 1:
        return first

    def merged(name):
        parts = [getattr(c, name) for c in clouds]
        return None if any(p is None for p in parts) else np.concatenate(parts)

    fields = ("xyz", "rgb", "intensity", "classification", "number_of_returns", "return_number")
    return PointCloud(
        **{k: merged(k) for k in fields}, crs=first.crs,
        source=f"{len(clouds)} tiles: " + ", ".join(c.source for c in clouds),
    )  # fmt: skip

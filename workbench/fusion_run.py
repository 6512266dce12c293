"""Reading a fusion run folder (the output of ``workbench fusion``), as every modeling
path that starts from rasters does."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rasterio.crs import CRS

from .errors import InputError
from .raster import BUILDING, TREE, Grid, class_codes, raster_header, read_raster

BANDS = {"ortho": 3, "class_prob": 4}  # rasters with more than one band


@dataclass
class FusionRun:
    """The rasters of a fusion run on their shared grid.

    Attributes
    ----------
    folder : Path
    rasters : {name: (B, H, W) array}
        As read (float32 heights with NaN unknown, uint8 colour and classes).
    grid : Grid
    crs : rasterio CRS or None
    record : dict
        fusion.json ({} if it is missing or unreadable).
    """

    folder: Path
    rasters: dict
    grid: Grid
    crs: object
    record: dict

    @property
    def mode(self) -> str | None:
        """How the run was made ("depth maps", "point cloud", ...), if it says."""
        mode = self.record.get("mode")
        return mode if isinstance(mode, str) else None

    @property
    def from_points(self) -> bool:
        return self.mode == "point cloud"

    def band(self, name: str) -> np.ndarray:
        """(H, W) first band of ``name``; heights as float64."""
        data = self.rasters[name][0]
        return data.astype(np.float64) if data.dtype.kind == "f" else data

    @property
    def rgb(self) -> np.ndarray:
        """(H, W, 3) uint8 ortho colour."""
        return np.moveaxis(self.rasters["ortho"], 0, -1)


def read_fusion_run(
    folder: str | Path, names: tuple[str, ...], window: tuple[slice, slice] | None = None
) -> FusionRun:
    """Read the rasters ``names`` ("ortho", "dsm", "dtm", "ndsm", "class_prob", "class")
    of a fusion run, checked to share one grid and CRS; with ``window`` ((rows, cols)
    slices of that grid) only those cells, on their own grid.

    Raises
    ------
    InputError
        Naming the missing or mismatched file.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, None, "no such fusion folder")
    out, grid, crs, first = {}, None, None, None
    for name in names:
        path = folder / f"{name}.tif"
        if not path.exists():
            raise InputError(path, None, "missing: not the output folder of `workbench fusion`")
        data, g, c = read_raster(path, window=window)
        if grid is None:
            grid, crs, first = g, c, path.name
        elif g != grid:
            raise InputError(path, "transform", f"grid differs from {folder}/{first}'s")
        elif c != crs:
            raise InputError(path, "crs", f"CRS differs from {folder}/{first}'s")
        if name in BANDS and data.shape[0] != BANDS[name]:
            raise InputError(path, "bands", f"expected {BANDS[name]} bands, got {data.shape[0]}")
        out[name] = data
    return FusionRun(folder, out, grid, crs, _record(folder / "fusion.json"))


ONE_CELL = (slice(0, 1), slice(0, 1))


def checked_fusion_run(folder: str | Path, names: tuple[str, ...], *, classes: bool) -> FusionRun:
    """What :func:`read_fusion_run` refuses of the rasters ``names``, and with
    ``classes`` of the class map when there is one (:func:`class_map`), checked on the
    grid's first cell: a command's check of its inputs reads no whole-grid raster.
    Returns the run with its whole grid and CRS, and no raster."""
    cell = read_fusion_run(folder, names, ONE_CELL)
    if classes:
        class_map(folder, cell.grid, ONE_CELL)
    grid = raster_header(Path(folder) / f"{names[0]}.tif")[0]
    for name in names[1:]:  # the first cells agree: so must the sizes
        path = Path(folder) / f"{name}.tif"
        if raster_header(path)[0] != grid:
            raise InputError(path, "transform", f"grid differs from {folder}/{names[0]}.tif's")
    return FusionRun(cell.folder, {}, grid, cell.crs, cell.record)


def _record(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return {}
    return doc if isinstance(doc, dict) else {}


def fusion_grid(folder: str | Path) -> Grid:
    """The grid of a fusion run's rasters (its ``dsm.tif``'s), read from the header alone."""
    return fusion_header(folder)[0]


def fusion_header(folder: str | Path) -> tuple[Grid, CRS | None]:
    """The grid and CRS of a fusion run's rasters (its ``dsm.tif``'s header)."""
    path = Path(folder) / "dsm.tif"
    if not path.exists():
        raise InputError(path, None, "missing: not the output folder of `workbench fusion`")
    grid, _, crs = raster_header(path)
    return grid, crs


def class_map(
    fusion_dir: Path, grid: Grid, window: tuple[slice, slice] | None = None
) -> np.ndarray | None:
    """(H, W) the class codes of the fusion's class map (``class.tif``) on ``grid`` (the
    cells ``window`` of the run's grid, if given), or None when the run has none (a
    cloud's, a run from another tool)."""
    return _optional_band(fusion_dir, "class", grid, window)


def hidden_ceiling(
    fusion_dir: Path, grid: Grid, window: tuple[slice, slice] | None = None
) -> np.ndarray | None:
    """(H, W) float64 the fusion's ceiling over the cells no view saw (``ceiling.tif``,
    metres, NaN elsewhere: :mod:`fusion.hidden_ceiling`) on ``grid`` (the cells
    ``window`` of the run's grid, if given), or None when the run has none (a cloud's,
    a mesh's, an older run's)."""
    band = _optional_band(fusion_dir, "ceiling", grid, window)
    return None if band is None else band.astype(np.float64)


def _optional_band(fusion_dir: Path, name: str, grid: Grid, window) -> np.ndarray | None:
    """The first band of the fusion's ``name``.tif on ``grid``, or None without one."""
    path = Path(fusion_dir) / f"{name}.tif"
    if not path.exists():
        return None
    run = read_fusion_run(fusion_dir, (name,), window)
    if run.grid != grid:
        raise InputError(path, "transform", "grid differs from the fusion's other rasters'")
    return run.rasters[name][0]


def tree_cells(classes: np.ndarray | None, class_prob: np.ndarray) -> np.ndarray:
    """(H, W) bool the cells the fusion calls tree: its class map's (``classes``, of
    :func:`class_map`; on seeds 0-2 it calls 7 segments of crowns tree that the
    probabilities, cell by cell, give to building, and no building), or with no class
    map those whose tree probability outweighs building's in ``class_prob`` (4, H, W)."""
    if classes is not None:
        return classes == TREE
    prob = np.nan_to_num(np.asarray(class_prob, np.float64))
    return prob[TREE - 1] > prob[BUILDING - 1]


def building_cells(classes: np.ndarray | None, class_prob: np.ndarray) -> np.ndarray:
    """(H, W) bool the cells the fusion calls building: its class map's (``classes``, of
    :func:`class_map`), or with no class map those whose most probable class in
    ``class_prob`` (4, H, W) is building."""
    if classes is not None:
        return classes == BUILDING
    return class_codes(class_prob) == BUILDING

"""A survey's tiles read one at a time, their kept returns spilled to disk, and the returns
of a block of the grid read back: a cloud larger than memory, rasterised block by block.

A survey is delivered as tiles (:func:`~fusion.point_clouds.cloud_files`). Each tile is
read once (:func:`~fusion.point_clouds.read_points`), its noise and the returns outside
``--bounds`` dropped, and the rest written as NumPy arrays in a scratch folder, which a
block maps and reads only its returns from. What the whole survey decides (its grid's
cell, the intensity that is white, whether its ground class makes the DTM) is gathered
while the tiles are read, so that every block decides it alike.
"""

from __future__ import annotations

import errno
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from workbench.errors import InputError, WorkbenchError
from workbench.progress import progress
from workbench.raster import Grid

from .options import FusionOptions
from .point_clouds import PointCloud, check_same_crs, cloud_files, read_points

ASPRS_NOISE = (7, 18)
ASPRS_GROUND = 2
GROUND_RETURNS = 100  # a survey with fewer ground returns has no ground class to use
RETURNS_PER_CELL = 1.0  # the default cell holds this many returns on average
ATTRIBUTES = ("rgb", "intensity", "classification", "number_of_returns", "return_number")
INTENSITY_LEVELS = 1 << 16  # LAS intensities are 16-bit


@dataclass
class SpilledTile:
    """One tile's kept returns in ``folder`` (``xyz.npy`` and an array per attribute)."""

    folder: Path
    lo: np.ndarray  # (2,) the kept returns' least x and y
    hi: np.ndarray  # (2,) their largest
    n: int


@dataclass
class Survey:
    """The tiles of one survey, read once and spilled (:func:`spilled_survey`).

    Attributes
    ----------
    attributes : the attributes every tile has (those of :class:`PointCloud` but xyz)
    unit : metres per unit of the CRS (1 without a projected CRS)
    covered : the area the returns cover, in the CRS's units squared
        (:func:`covered_area`), summed over the tiles
    intensity_counts : (65536,) returns per intensity, or None without intensities
    ground_returns : returns of the ground class (ASPRS 2)
    """

    files: list[Path]
    tiles: list[SpilledTile]
    crs: object
    attributes: tuple[str, ...]
    unit: float
    n_points: int
    covered: float
    intensity_counts: np.ndarray | None
    ground_returns: int
    source: str = ""

    @property
    def n_used(self) -> int:
        return sum(t.n for t in self.tiles)

    @property
    def density(self) -> float:
        """Returns per unit area where the survey has returns."""
        return self.n_used / max(self.covered, 1e-12)

    def default_gsd(self, returns_per_cell: float = RETURNS_PER_CELL) -> float:
        """The cell that holds ``returns_per_cell`` returns on average
        (:func:`cell_holding`; :func:`~fusion.points.default_gsd` of one cloud)."""
        return cell_holding(returns_per_cell, self.density)

    def grid(self, opts: FusionOptions) -> Grid:
        """The grid of ``opts.bounds``, else the one covering every kept return, at
        ``opts.gsd`` or the default cell."""
        lo = np.min([t.lo for t in self.tiles], axis=0)
        hi = np.max([t.hi for t in self.tiles], axis=0)
        return Grid.covering(np.stack([lo, hi]), opts.gsd or self.default_gsd(), opts.bounds)

    @property
    def ground_class(self) -> bool:
        """Whether the DTM comes from the ground class (else the morphological filter)."""
        return self.ground_returns > GROUND_RETURNS

    @property
    def intensity_white(self) -> float:
        """The intensity drawn white when a survey has no colour: the 99th percentile of
        its kept returns' (as :func:`numpy.percentile` of them all gives it)."""
        return percentile_of_counts(self.intensity_counts, 99.0) or 1.0

    def returns_in(self, grid: Grid, rows: slice, cols: slice) -> tuple[PointCloud, np.ndarray]:
        """The returns whose cell of ``grid`` (the nearest border cell for those outside
        it) lies in ``rows`` x ``cols``, and those cells' flat indices in that window.

        Returns
        -------
        cloud : PointCloud of the returns, tile after tile
        cells : (N,) int64, row * width + col within the window
        """
        window = grid.window(rows, cols)
        x0, y0, x1, y1 = window.bounds
        parts, cells = [], []
        for t in self.tiles:
            # every kept return lies on the grid (:meth:`grid`); a cell's width of slack
            # for the rounding of a return on a cell's edge
            if (t.hi[0] < x0 - grid.gsd or t.lo[0] > x1 + grid.gsd or
                    t.hi[1] < y0 - grid.gsd or t.lo[1] > y1 + grid.gsd):  # fmt: skip
                continue
            xyz = np.load(t.folder / "xyz.npy", mmap_mode="r")
            r, c = grid.cell_index(xyz[:, 0], xyz[:, 1], clip=True)
            sel = np.flatnonzero((r >= rows.start) & (r < rows.stop) &
                                 (c >= cols.start) & (c < cols.stop))  # fmt: skip
            if not len(sel):
                continue
            part = {"xyz": np.asarray(xyz[sel])}
            for a in self.attributes:
                part[a] = np.asarray(np.load(t.folder / f"{a}.npy", mmap_mode="r")[sel])
            parts.append(part)
            cells.append((r[sel] - rows.start) * (cols.stop - cols.start) + c[sel] - cols.start)
        merged = {k: np.concatenate([p[k] for p in parts]) if parts else None
                  for k in ("xyz", *self.attributes)}  # fmt: skip
        if merged["xyz"] is None:
            merged["xyz"] = np.zeros((0, 3))
        cloud = PointCloud(**{k: merged.get(k) for k in ("xyz", *ATTRIBUTES)}, crs=self.crs,
                           source=self.source)  # fmt: skip
        return cloud, np.concatenate(cells) if cells else np.zeros(0, np.int64)


def cell_holding(returns_per_cell: float, density: float) -> float:
    """The side of the cell that holds ``returns_per_cell`` returns at ``density`` returns
    per unit area, rounded to two significant digits."""
    return float(f"{np.sqrt(returns_per_cell / density):.2g}")


def covered_area(xy: np.ndarray) -> float:
    """The area the points ``xy`` (N, 2) cover: the coarse cells of twice their mean
    spacing that hold one, so that water and a tile's empty corners are not counted."""
    lo = xy.min(axis=0)
    span = np.maximum(np.ptp(xy, axis=0), 1e-9)
    coarse = 2.0 * float(np.sqrt(span[0] * span[1] / len(xy)))
    ij = np.floor((xy - lo) / coarse).astype(np.int64)
    occupied = len(np.unique(ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]))
    return occupied * coarse * coarse


def percentile_of_counts(counts: np.ndarray | None, q: float) -> float:
    """The ``q``-th percentile (linear, as :func:`numpy.percentile`) of the integers whose
    histogram is ``counts`` (``counts[v]`` of the value ``v``); 0 for no values."""
    if counts is None or counts.sum() == 0:
        return 0.0
    cum = np.cumsum(counts)
    rank = (cum[-1] - 1) * q / 100.0
    lo = int(np.floor(rank))
    below, above = np.searchsorted(cum, [lo, min(lo + 1, cum[-1] - 1)], side="right")
    return float(below + (rank - lo) * (above - below))


def kept_returns(cloud: PointCloud, opts: FusionOptions) -> np.ndarray:
    """(N,) bool: the returns that are not noise and lie inside ``opts.bounds``."""
    xyz = cloud.xyz
    keep = np.ones(len(xyz), bool)
    if cloud.classification is not None:
        keep &= ~np.isin(cloud.classification, ASPRS_NOISE)
    if opts.bounds is not None:
        x0, y0, x1, y1 = opts.bounds
        keep &= (xyz[:, 0] >= x0) & (xyz[:, 0] < x1) & (xyz[:, 1] >= y0) & (xyz[:, 1] < y1)
    return keep


def spilled_survey(paths, opts: FusionOptions, crs: str | None, scratch: Path) -> Survey:
    """Read every tile of ``paths`` once, keep its returns that are not noise and lie in
    ``opts.bounds``, and write them to ``scratch``; memory follows the largest tile.

    Raises
    ------
    InputError
        An unreadable or empty tile, tiles whose CRSs differ (naming both), or no return
        inside the bounds.
    """
    files = cloud_files(paths)
    tiles, first, n_points, covered, ground = [], None, 0, 0.0, 0
    attributes = set(ATTRIBUTES)
    counts = np.zeros(INTENSITY_LEVELS, np.int64)
    for i, f in enumerate(progress(files, "fusion: reading the tiles")):
        cloud = read_points(f, crs)
        if first is None:
            first = cloud
        check_same_crs(cloud, first)
        n_points += len(cloud.xyz)
        keep = kept_returns(cloud, opts)
        attributes &= {a for a in ATTRIBUTES if getattr(cloud, a) is not None}
        if not keep.any():
            continue
        folder = Path(scratch) / f"tile_{i:05d}"
        xyz = cloud.xyz[keep]
        _spill(folder, {"xyz": xyz, **{a: getattr(cloud, a)[keep] for a in ATTRIBUTES
                                      if getattr(cloud, a) is not None}})  # fmt: skip
        if cloud.intensity is not None:
            counts += np.bincount(np.clip(cloud.intensity[keep], 0, INTENSITY_LEVELS - 1)
                                  .astype(np.int64), minlength=INTENSITY_LEVELS)  # fmt: skip
        if cloud.classification is not None:
            ground += int(np.count_nonzero(cloud.classification[keep] == ASPRS_GROUND))
        covered += covered_area(xyz[:, :2])
        tiles.append(SpilledTile(folder, xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0),
                                 len(xyz)))  # fmt: skip
    if not tiles:
        raise InputError(files[0] if len(files) == 1 else first.source, "bounds",
                         "no points inside the bounds")  # fmt: skip
    c = first.crs
    unit = c.linear_units_factor[1] if c is not None and c.is_projected else 1.0
    source = first.source if len(files) == 1 else f"{len(files)} tiles: " + ", ".join(
        str(f) for f in files)  # fmt: skip
    return Survey(files, tiles, c, tuple(a for a in ATTRIBUTES if a in attributes), unit,
                  n_points, covered, counts if "intensity" in attributes else None, ground,
                  source)  # fmt: skip


def _spill(folder: Path, arrays: dict) -> None:
    """Write a tile's kept returns into ``folder``; a full disk is a one-line error."""
    try:
        folder.mkdir(parents=True)
        for name, a in arrays.items():
            np.save(folder / f"{name}.npy", a)
    except OSError as e:
        if e.errno != errno.ENOSPC:
            raise
        raise WorkbenchError(
            f"{folder.parent}: disk full while keeping the survey's returns (about 40 bytes "
            "a return, beside the output): free some space, or give --bounds"
        ) from None

"""North-up GeoTIFF rasters that always travel with their grid and CRS.

A :class:`Grid` is the ortho grid of the workbench: an axis-aligned, north-up
array of square cells. Row 0 is the northern edge; cell centres are at
``(xmin + (col + 0.5) * gsd, ymax - (row + 0.5) * gsd)``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
import rasterio.shutil
from rasterio.crs import CRS
from rasterio.errors import CRSError, RasterioIOError
from rasterio.transform import Affine
from rasterio.windows import Window

from .errors import InputError
from .parallel import default_workers


@dataclass(frozen=True)
class Grid:
    """A north-up grid of square cells.

    Attributes
    ----------
    xmin, ymax : float
        World coordinates of the north-west corner of the grid (metres).
    gsd : float
        Cell size (ground sampling distance), metres.
    width, height : int
        Number of columns and rows.
    """

    xmin: float
    ymax: float
    gsd: float
    width: int
    height: int

    @classmethod
    def from_bounds(cls, xmin: float, ymin: float, xmax: float, ymax: float, gsd: float) -> Grid:
        """The grid of cells of size ``gsd`` covering the bounds (rounded outwards)."""
        if gsd <= 0:
            raise ValueError(f"gsd must be positive, got {gsd}")
        width = int(np.ceil((xmax - xmin) / gsd - 1e-9))
        height = int(np.ceil((ymax - ymin) / gsd - 1e-9))
        return cls(float(xmin), float(ymax), float(gsd), width, height)

    @classmethod
    def covering(cls, xy: np.ndarray, gsd: float, bounds=None) -> Grid:
        """The grid of ``bounds`` (xmin, ymin, xmax, ymax) if given, else of cells of size
        ``gsd`` covering every point of ``xy`` (N, 2), the easternmost and northernmost
        ones included."""
        if bounds is not None:
            return cls.from_bounds(*bounds, gsd)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        return cls.from_bounds(lo[0], lo[1], hi[0] + 1e-6, hi[1] + 1e-6, gsd)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) in world metres."""
        return (
            self.xmin,
            self.ymax - self.height * self.gsd,
            self.xmin + self.width * self.gsd,
            self.ymax,
        )

    @property
    def transform(self) -> Affine:
        return Affine(self.gsd, 0.0, self.xmin, 0.0, -self.gsd, self.ymax)

    def cell_center(self, row: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World x and y of the centres of the cells (``row``, ``col``)."""
        x = self.xmin + (np.asarray(col) + 0.5) * self.gsd
        y = self.ymax - (np.asarray(row) + 0.5) * self.gsd
        return x, y

    def window(self, rows: slice, cols: slice) -> Grid:
        """The grid of the cells ``rows`` x ``cols`` (slices with start and stop)."""
        return Grid(self.xmin + cols.start * self.gsd, self.ymax - rows.start * self.gsd,
                    self.gsd, cols.stop - cols.start, rows.stop - rows.start)  # fmt: skip

    def window_of(self, bounds, pad: int = 0) -> tuple[slice, slice] | None:
        """The rows and columns of the cells a box (xmin, ymin, xmax, ymax, world metres)
        touches, ``pad`` cells around, clipped to the grid (None where none is left)."""
        x0, y0, x1, y1 = bounds
        c0 = max(int(np.floor((x0 - self.xmin) / self.gsd)) - pad, 0)
        c1 = min(int(np.ceil((x1 - self.xmin) / self.gsd)) + pad, self.width)
        r0 = max(int(np.floor((self.ymax - y1) / self.gsd)) - pad, 0)
        r1 = min(int(np.ceil((self.ymax - y0) / self.gsd)) + pad, self.height)
        return (slice(r0, r1), slice(c0, c1)) if r1 > r0 and c1 > c0 else None

    def tiles(self, size: int) -> list[tuple[slice, slice]]:
        """Rows and columns of the tiles of ``size`` x ``size`` cells covering the grid,
        row by row (the last of a row or column smaller)."""
        return [(slice(r, min(r + size, self.height)), slice(c, min(c + size, self.width)))
                for r in range(0, self.height, size)
                for c in range(0, self.width, size)]  # fmt: skip

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World x and y of every cell centre, each of shape (height, width)."""
        xs, _ = self.cell_center(0, np.arange(self.width))
        _, ys = self.cell_center(np.arange(self.height), 0)
        return np.meshgrid(xs, ys)

    def world_to_cell(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column (float, cell centres at integers) of world points."""
        col = (np.asarray(x) - self.xmin) / self.gsd - 0.5
        row = (self.ymax - np.asarray(y)) / self.gsd - 0.5
        return row, col

    def cell_index(
        self, x: np.ndarray, y: np.ndarray, *, clip: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Row and column (int64) of the cell containing each world point.

        With ``clip``, points outside the grid take the nearest border cell; otherwise
        their indices fall outside ``[0, height)`` x ``[0, width)``.
        """
        row, col = self.world_to_cell(x, y)
        row = np.floor(row + 0.5).astype(np.int64)
        col = np.floor(col + 0.5).astype(np.int64)
        if clip:
            row = np.clip(row, 0, self.height - 1)
            col = np.clip(col, 0, self.width - 1)
        return row, col

    def contains(self, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """Whether integer cell indices lie inside the grid."""
        return (row >= 0) & (row < self.height) & (col >= 0) & (col < self.width)

    @classmethod
    def from_transform(cls, transform: Affine, width: int, height: int) -> Grid:
        if abs(transform.b) > 1e-12 or abs(transform.d) > 1e-12:
            raise ValueError("raster is rotated; only north-up rasters are supported")
        if abs(transform.a + transform.e) > 1e-9 * abs(transform.a) or transform.a <= 0:
            raise ValueError("raster cells are not square and north-up")
        return cls(transform.c, transform.f, transform.a, width, height)


def decimated_cells(
    rows: slice, cols: slice, f: int, origin: tuple[int, int] = (0, 0)
) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Where the grid's every ``f``-th cell (rows and columns multiples of ``f``) among
    the cells ``rows`` x ``cols`` lies: in an array of a window starting at the grid's
    cell ``origin``, and in the grid decimated by ``f``. A mosaic put together window by
    window is then the whole grid's ``[::f, ::f]``.

    Returns
    -------
    inside : (slice, slice)
        Of the window's array (steps of ``f``).
    at : (slice, slice)
        Of the decimated grid's.
    """
    inside, at = [], []
    for cells, o in zip((rows, cols), origin, strict=True):
        first = -(-cells.start // f) * f
        n = len(range(first, cells.stop, f))
        inside.append(slice(first - o, cells.stop - o, f))
        at.append(slice(first // f, first // f + n))
    return (inside[0], inside[1]), (at[0], at[1])


def shifted(image: np.ndarray, offset: int, axis: int, fill=0) -> np.ndarray:
    """``image`` ((H, W)) with each cell taking the value ``offset`` cells along ``axis``
    from it; ``fill`` past the edge."""
    out = np.full_like(image, fill)
    src = [slice(None)] * 2
    dst = [slice(None)] * 2
    if offset > 0:
        src[axis], dst[axis] = slice(offset, None), slice(None, -offset)
    else:
        src[axis], dst[axis] = slice(None, offset), slice(-offset, None)
    out[tuple(dst)] = image[tuple(src)]
    return out


def parse_crs(value, *, path: str | os.PathLike, field: str = "crs") -> CRS:
    """Parse an EPSG code (``"EPSG:32631"``, ``32631``), WKT or PROJ string.

    Raises
    ------
    InputError
        Naming ``path`` and ``field`` when the CRS is unknown.
    """
    try:
        crs = CRS.from_user_input(value)
    except (CRSError, TypeError, ValueError) as exc:
        raise InputError(path, field, f"unknown CRS {str(value)[:60]!r} ({exc})") from None
    return crs


CLASS_CODES = (0, 1, 2, 3, 4)  # no data, ground, grass, tree, building
GROUND, GRASS, TREE, BUILDING = 1, 2, 3, 4


def class_codes(class_prob: np.ndarray, band: int = 256) -> np.ndarray:
    """(H, W) uint8 class codes 1-4 of (4, H, W) probabilities (ground, grass, tree,
    building; NaN unseen), 0 where unseen: each cell's most probable class. Taken in
    bands of ``band`` rows: the int64 arg-maxima of a whole city's grid were 150 MiB."""
    codes = np.zeros(class_prob.shape[1:], np.uint8)
    for r0 in range(0, codes.shape[0], band):
        prob = class_prob[:, r0 : r0 + band]
        seen = np.isfinite(prob[0])
        codes[r0 : r0 + band][seen] = (np.argmax(np.nan_to_num(prob), axis=0) + 1)[seen]
    return codes


def check_class_codes(data: np.ndarray, path, field: str | None = None) -> np.ndarray:
    """``data`` unchanged if every value is a class code 0-4, else a one-line error naming
    ``path``, ``field`` and the first codes found outside (a class raster from another
    tool, with its own scheme, would otherwise be scored as if it were ours)."""
    bad = np.setdiff1d(np.unique(data), CLASS_CODES)
    if bad.size:
        raise InputError(
            path, field, f"class codes {bad[:5].tolist()} not in 0-4 (0 no data, 1 ground, "
            "2 grass, 3 tree, 4 building)",
        )  # fmt: skip
    return data


def crs_name(crs: CRS | None) -> str:
    """A short name of a CRS for messages: ``EPSG:n``, else the start of its WKT."""
    if crs is None:
        return "no CRS"
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.to_wkt()[:60] + "..."


def write_raster(
    path: str | os.PathLike,
    data: np.ndarray,
    grid: Grid,
    crs: CRS | None,
    *,
    nodata: float | int | None = None,
    descriptions: list[str] | None = None,
) -> None:
    """Write a north-up Cloud-Optimized GeoTIFF (tiled, compressed, with overviews).

    Parameters
    ----------
    path : path
        Output file.
    data : (H, W) or (B, H, W) ndarray
        Pixel values; float rasters use NaN as nodata.
    grid : Grid
        The grid the data lies on; ``data`` must have its shape.
    crs : rasterio.crs.CRS or None
        Coordinate reference system (None for a local frame).
    nodata : number, optional
        Nodata value; defaults to NaN for float data, none for integer data.
    descriptions : list of str, optional
        One description per band (for example the class names).
    """
    arr = data[None] if data.ndim == 2 else data
    if arr.shape[1:] != grid.shape:
        raise ValueError(f"data shape {arr.shape[1:]} does not match grid {grid.shape}")
    with rasterio.open(path, "w", **cog_profile(grid, crs, arr.dtype, arr.shape[0], nodata)) as dst:
        dst.write(arr)
        if descriptions:
            for i, d in enumerate(descriptions, start=1):
                dst.set_band_description(i, d)


def cog_profile(grid: Grid, crs: CRS | None, dtype, count: int, nodata=None) -> dict:
    """The profile of :func:`write_raster`'s Cloud-Optimized GeoTIFFs: tiled, compressed,
    with overviews inside, readable in parts over HTTP; ``nodata`` NaN by default for
    float data, none for integer data."""
    floating = np.issubdtype(dtype, np.floating)
    if nodata is None and floating:
        nodata = float("nan")
    image = floating or (np.dtype(dtype) == np.uint8 and count == 3)
    return dict(
        driver="COG",
        width=grid.width,
        height=grid.height,
        count=count,
        dtype=dtype,
        crs=crs,
        transform=grid.transform,
        nodata=nodata,
        compress="deflate",
        predictor="FLOATING_POINT" if floating else "STANDARD",
        blocksize=256,
        # heights and colours average into an overview; classes and ids must not
        overview_resampling="average" if image else "nearest",
        # GDAL compresses the tiles on the process's cores; the file is byte for byte the
        # one a single thread writes
        num_threads=default_workers(),
    )


class WindowedRaster:
    """A raster written window by window, the Cloud-Optimized GeoTIFF of
    :func:`write_raster` once closed: the whole raster is never in memory.

    The windows go into a tiled GeoTIFF beside ``path``, opened for each window and
    closed after it (GDAL keeps a file's written blocks in its cache until then, up to 5 %
    of the machine's memory), which GDAL copies into the COG, overviews included, block
    by block when :meth:`close` is called.

    Parameters
    ----------
    path : path
    grid : Grid
    crs : CRS or None
    dtype, count
        The raster's data type and number of bands.
    nodata, descriptions
        As for :func:`write_raster`.
    reopen : bool
        Keep the windows a run before wrote into the staging file, if it is there (a
        resumed run's), instead of starting an empty one.
    """

    def __init__(self, path, grid: Grid, crs: CRS | None, dtype, count: int = 1, *,
                 nodata=None, descriptions: list[str] | None = None,
                 reopen: bool = False):  # fmt: skip
        self.path = Path(path)
        self.profile = cog_profile(grid, crs, dtype, count, nodata)
        self.staging = self.path.with_name(f".{self.path.name}.windows.tif")
        if reopen and self.staging.exists():
            return
        cog_only = ("driver", "blocksize", "overview_resampling", "predictor")
        staging = {k: v for k, v in self.profile.items() if k not in cog_only}
        with _gdal_cache(), rasterio.open(self.staging, "w", driver="GTiff", tiled=True,
                                          blockxsize=256, blockysize=256, bigtiff="IF_SAFER",
                                          **staging) as dst:  # fmt: skip
            for i, d in enumerate(descriptions or [], start=1):
                dst.set_band_description(i, d)

    def write(self, data: np.ndarray, rows: slice, cols: slice) -> None:
        """Write ``data`` ((h, w) or (B, h, w)) at the cells ``rows`` x ``cols``."""
        arr = data[None] if data.ndim == 2 else data
        window = Window(cols.start, rows.start, cols.stop - cols.start, rows.stop - rows.start)
        with _gdal_cache(), rasterio.open(self.staging, "r+") as dst:
            dst.write(arr, window=window)

    def read(self, rows: slice, cols: slice) -> np.ndarray:
        """(B, h, w) the cells ``rows`` x ``cols`` as written so far (0, or the nodata
        value, where nothing was)."""
        window = Window(cols.start, rows.start, cols.stop - cols.start, rows.stop - rows.start)
        with _gdal_cache(), rasterio.open(self.staging) as src:
            return src.read(window=window)

    def close(self) -> None:
        """The COG at ``path``; the staging file removed."""
        options = {k: self.profile[k] for k in ("compress", "predictor", "blocksize",
                                               "overview_resampling", "num_threads")}  # fmt: skip
        try:
            with _gdal_cache():
                rasterio.shutil.copy(self.staging, self.path, driver="COG", **options)
        finally:
            self.staging.unlink(missing_ok=True)

    def discard(self) -> None:
        """Remove the staging file (the run failed)."""
        self.staging.unlink(missing_ok=True)


class RasterWindows:
    """A one-band raster on disk that reads the cells it is sliced at: ``r[rows, cols]``
    (slices with start and stop) is what the whole array sliced so would be, NaN at its
    nodata, without the whole array in memory.

    Parameters
    ----------
    path : path
    grid : Grid
        The raster's grid.
    as_float : bool
        As for :func:`read_raster` (heights of an integer raster).
    """

    def __init__(self, path, grid: Grid, *, as_float: bool = False):
        self.path, self.grid, self.as_float = Path(path), grid, as_float

    @property
    def shape(self) -> tuple[int, int]:
        return self.grid.shape

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        return read_raster(self.path, window=key, as_float=self.as_float)[0][0]


GDAL_CACHE_MB = 256  # GDAL's block cache while windows are written and copied


def _gdal_cache():
    return rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB)


def read_decimated(path, longest: int) -> np.ndarray:
    """(B, h, w) a raster read at most ``longest`` cells on its longer side, from its
    overviews where it has them (a preview of a raster too large to hold whole)."""
    with rasterio.open(path) as src:
        f = max(1, int(np.ceil(max(src.height, src.width) / longest)))
        shape = (src.count, -(-src.height // f), -(-src.width // f))
        return src.read(out_shape=shape, masked=False)


def raster_header(
    path: str | os.PathLike, field: str | None = None
) -> tuple[Grid, int, CRS | None]:
    """A raster's grid, band count and CRS, its cells not read.

    Raises
    ------
    InputError
        When the file is missing, unreadable or not north-up (naming ``field``).
    """
    if not os.path.exists(path):
        raise InputError(path, field, "file not found")
    try:
        with rasterio.open(path) as src:
            return Grid.from_transform(src.transform, src.width, src.height), src.count, src.crs
    except (RasterioIOError, ValueError) as exc:
        raise InputError(path, field, f"not a readable north-up raster ({exc})") from None


def read_raster(
    path: str | os.PathLike,
    *,
    field: str | None = None,
    as_float: bool = False,
    window: tuple[slice, slice] | None = None,
):
    """Read a north-up GeoTIFF, or a window of it, its nodata honoured.

    Cells the file marks as nodata (its nodata value, NaN, or its mask band) become NaN in
    float rasters, and 0, the class rasters' "no data", in integer ones.

    Parameters
    ----------
    path : path
    field : str, optional
        Named in the errors (the scene or truth field the file is read for).
    as_float : bool
        Read an integer raster as float with NaN at its nodata: heights (an int16 DEM with
        nodata -32768 is common), never classes.
    window : (rows, cols) slices, optional
        The cells to read (with start and stop, within the raster); the grid returned is
        theirs.

    Returns
    -------
    data : (B, H, W) ndarray
    grid : Grid
    crs : rasterio.crs.CRS or None

    Raises
    ------
    InputError
        When the file is missing, unreadable or not north-up.
    """
    if not os.path.exists(path):
        raise InputError(path, field, "file not found")
    try:
        with rasterio.open(path) as src:
            grid = Grid.from_transform(src.transform, src.width, src.height)
            if window is not None:
                masked = src.read(masked=True, window=Window.from_slices(*window))
                grid = grid.window(*window)
            else:
                masked = src.read(masked=True)
            crs = src.crs
    except RasterioIOError as exc:
        raise InputError(path, field, f"not a readable raster ({exc})") from None
    except ValueError as exc:
        raise InputError(path, field, str(exc)) from None
    if masked.dtype.kind == "f" or as_float:
        wide = masked.dtype.itemsize >= 8 or (
            masked.dtype.kind in "iu" and masked.dtype.itemsize >= 4
        )
        # no copy where the file is float32 already: filled() makes the one copy (a
        # city's class probabilities are 100 MB)
        data = masked.astype(np.float64 if wide else np.float32, copy=False).filled(np.nan)
    else:
        data = masked.filled(0)
    return data, grid, crs

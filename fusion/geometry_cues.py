"""Geometric cues of the fused surface for the per-view forest (not in the paper).

Colour alone calls a moss-green roof a tree and an autumn crown a roof. Their shapes
differ: a roof is planar over a metre or two (or two planes meeting at a ridge), a crown
is lumpy; and the views see a crown at depths that scatter (the rim, leaves in front of
others) where they agree on a roof. Three cues per cell say so:

- ``plane_residual`` at two scales: the RMS residual of the least-squares plane through
  the fused DSM in a window of about 1.25 m and 2.25 m;
- ``height_spread``: the interquartile range of the heights the views observed in the
  cell (weighted as the DSM's median is).

Each view pixel takes the cues of the cell its point falls in, beside its Sigma Points.
"""

from __future__ import annotations

import cv2
import numpy as np

from workbench.raster import Grid
from workbench.robust import plane_residual_from_moments

CUES = ("plane_residual_1.25m", "plane_residual_2.25m", "height_spread")
WINDOWS_M = (1.25, 2.25)
UNKNOWN = -1.0  # the forest's value for a cue no cell gives (NaN it cannot split on)
TILE_CELLS = 512  # plane_residual's tiles: 512 x 512 cells of float64 moments, ~45 MB


def plane_residual(dsm: np.ndarray, size: int, tile: int = TILE_CELLS) -> np.ndarray:
    """(H, W) float32 RMS residual of the least-squares plane z = a x + b y + c through
    the known cells of the ``size`` x ``size`` window around each cell, metres; NaN
    where fewer than 6 cells are known.

    From box sums of the moments of x, y and z, so that it costs a few filters of the
    grid whatever the window; in tiles of ``tile`` x ``tile`` cells with the window's
    half as a margin, so that its float64 moments (some 160 bytes a cell) are a tile's,
    not a city's.
    """
    known = np.isfinite(dsm)
    if not known.any():
        return np.full(dsm.shape, np.nan, np.float32)
    origin = float(np.median(np.asarray(dsm[known], np.float64)))  # heights near 0
    out = np.empty(dsm.shape, np.float32)
    half = size // 2
    for r0 in range(0, dsm.shape[0], tile):
        for c0 in range(0, dsm.shape[1], tile):
            rs, cs = max(r0 - half, 0), max(c0 - half, 0)
            with_margin = dsm[rs : r0 + tile + half, cs : c0 + tile + half]
            res = _window_plane_residual(with_margin, size, origin)
            out[r0 : r0 + tile, c0 : c0 + tile] = res[r0 - rs : r0 - rs + tile,
                                                      c0 - cs : c0 - cs + tile]  # fmt: skip
    return out


def _window_plane_residual(dsm: np.ndarray, size: int, origin: float) -> np.ndarray:
    """:func:`plane_residual` of one tile with its margin (cells beyond the array count
    as unknown: the grid's own border), heights taken from ``origin``."""
    z = np.asarray(dsm, np.float64)
    known = np.isfinite(z)
    z = np.where(known, z - origin, 0.0)
    w = known.astype(np.float64)
    rows, cols = np.indices(z.shape, dtype=np.float64)

    def box(a):
        return cv2.boxFilter(a, cv2.CV_64F, (size, size), normalize=False,
                             borderType=cv2.BORDER_CONSTANT)  # fmt: skip

    n = box(w)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx, my, mz = (box(w * a) / n for a in (cols, rows, z))
        cxx = box(w * cols * cols) / n - mx * mx
        cyy = box(w * rows * rows) / n - my * my
        cxy = box(w * cols * rows) / n - mx * my
        cxz = box(w * cols * z) / n - mx * mz
        cyz = box(w * rows * z) / n - my * mz
        czz = box(w * z * z) / n - mz * mz
    rms = plane_residual_from_moments(cxx, cyy, cxy, cxz, cyz, czz)
    return np.where(n >= 6, rms, np.nan).astype(np.float32)


def window_cells(window_m: float, gsd: float) -> int:
    """An odd window of about ``window_m`` metres in cells of ``gsd`` metres, at least 3."""
    return max(3, int(round(window_m / gsd)) // 2 * 2 + 1)


def geometric_cues(dsm: np.ndarray, spread: np.ndarray, gsd: float) -> np.ndarray:
    """(3, H, W) float32 :data:`CUES` of every cell (NaN where unknown).

    Parameters
    ----------
    dsm : (H, W) float
        Fused heights, metres, NaN unknown.
    spread : (H, W) float
        Interquartile range of each cell's observed heights, metres.
    gsd : float
        Cell size, metres.
    """
    residuals = [plane_residual(dsm, window_cells(w, gsd)) for w in WINDOWS_M]
    return np.stack([*residuals, np.asarray(spread, np.float32)])


def cue_columns(cues: np.ndarray, xyz: np.ndarray, grid: Grid) -> np.ndarray:
    """(N, G) float32 the cues of the cell each point falls in, :data:`UNKNOWN` for
    cells without the cue.

    Parameters
    ----------
    cues : (G, H, W) float
    xyz : (N, 3) float
        Lifted pixels' points, world metres.
    """
    r, c = grid.cell_index(xyz[:, 0], xyz[:, 1], clip=True)
    values = cues[:, r, c].T
    return np.where(np.isfinite(values), values, UNKNOWN).astype(np.float32)

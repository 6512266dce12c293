"""Per-cell robust statistics over many observations, vectorised by sorting.

Observations arrive as flat arrays with a cell index each; cells are integers in
``[0, n_cells)``. Nothing loops over cells or observations in Python.
"""

from __future__ import annotations

import numpy as np


def group_count(cells: np.ndarray, n_cells: int) -> np.ndarray:
    """(n_cells,) number of observations per cell."""
    return np.bincount(cells, minlength=n_cells)


def group_mean(cells: np.ndarray, values: np.ndarray, n_cells: int) -> np.ndarray:
    """(n_cells, ...) mean of ``values`` per cell, NaN for empty cells."""
    count = np.bincount(cells, minlength=n_cells).astype(np.float64)
    v = values.reshape(len(values), int(np.prod(values.shape[1:])))
    sums = np.stack([np.bincount(cells, v[:, k], minlength=n_cells) for k in range(v.shape[1])], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = sums / count[:, None]
    return mean.reshape((n_cells,) + values.shape[1:])


def group_median(cells: np.ndarray, values: np.ndarray, n_cells: int) -> np.ndarray:
    """(n_cells,) median of scalar ``values`` per cell (mean of the two middle values
    for even counts), NaN for empty cells."""
    if len(cells) == 0:
        return np.full(n_cells, np.nan)
    layout = CellLayout.of(cells, n_cells)
    return layout.medians(values[layout.order][None])[0]


class CellLayout:
    """Observations grouped by cell: ``order`` sorts them by cell (stably: in their
    order within a cell), ``count`` and ``start`` give each cell's run in that order.

    Statistics of several value columns share it (:meth:`medians`); a cell's values are
    sorted on their own, a few thousand cells at a time, rather than all observations
    by one key per column.
    """

    BLOCK = 1 << 18  # padded values sorted at once: 2 MB of float64 per column

    def __init__(self, order: np.ndarray, count: np.ndarray):
        self.order, self.count = order, count
        self.start = np.cumsum(count) - count

    @classmethod
    def of(cls, cells: np.ndarray, n_cells: int) -> CellLayout:
        """The layout of ``cells`` (N,) int in ``[0, n_cells)``."""
        return cls(np.argsort(cells, kind="stable"), np.bincount(cells, minlength=n_cells))

    def spread(self, per_cell: np.ndarray) -> np.ndarray:
        """(..., N) each cell's value of ``per_cell`` (..., n_cells) repeated over its
        observations, in the layout's order."""
        return np.repeat(per_cell, self.count, axis=-1)

    def medians(self, values: np.ndarray) -> np.ndarray:
        """(P, n_cells) float64 median of each row of ``values`` (P, N), in the
        layout's order, per cell (mean of the two middle values for even counts), NaN
        for empty cells.

        Cells of up to 2**b observations are padded with +inf to 2**b and sorted as
        rows: no sort of all N, and no more than twice the values' memory per block.
        """
        n_rows = values.shape[0]
        out = np.full((n_rows, len(self.count)), np.nan)
        cells = np.flatnonzero(self.count)
        count = self.count[cells]
        width, lower = 1, 0
        while len(count) and lower < count.max():
            in_bucket = np.flatnonzero((count > lower) & (count <= width))
            step = max(1, self.BLOCK // width)
            for at in (in_bucket[i : i + step] for i in range(0, len(in_bucket), step)):
                out[:, cells[at]] = self._middle(values, self.start[cells[at]], count[at], width)
            lower, width = width, 2 * width
        return out

    @staticmethod
    def _middle(values, start, count, width) -> np.ndarray:
        """(P, n) the medians of ``n`` cells of ``count`` <= ``width`` observations from
        ``start`` in ``values`` (P, N)."""
        k = np.arange(width)
        valid = k < count[:, None]
        block = values[:, np.where(valid, start[:, None] + k, 0)]  # (P, n, width)
        if block.dtype.kind != "f":  # integers: +inf pads floats only
            block = block.astype(np.float64)
        block[:, ~valid] = np.inf
        block.sort(axis=-1)
        rows = np.arange(len(count))
        lo, hi = block[:, rows, (count - 1) // 2], block[:, rows, count // 2]
        return 0.5 * (lo.astype(np.float64) + hi)


def group_weighted_median(
    cells: np.ndarray, values: np.ndarray, weights: np.ndarray, n_cells: int
) -> np.ndarray:
    """(n_cells,) weighted median of scalar ``values`` per cell, NaN for empty cells
    (:func:`group_weighted_quantile` at 0.5). With equal weights this is
    :func:`group_median`."""
    return group_weighted_quantile(cells, values, weights, n_cells, 0.5)


def group_weighted_quantile(
    cells: np.ndarray, values: np.ndarray, weights: np.ndarray, n_cells: int, q
) -> np.ndarray:
    """Weighted ``q`` quantile of scalar ``values`` per cell, NaN for empty cells.

    The value at which the cell's cumulative weight (in value order) reaches ``q`` of
    its total; where it reaches exactly that, the mean of that value and the next.
    Several quantiles share one sort.

    Parameters
    ----------
    cells : (N,) int
    values : (N,) float
    weights : (N,) float, positive
    n_cells : int
    q : float, or sequence of floats
        In (0, 1).

    Returns
    -------
    (n_cells,) for one ``q``; (len(q), n_cells) for a sequence.
    """
    qs = np.atleast_1d(np.asarray(q, dtype=np.float64))
    out = np.full((len(qs), n_cells), np.nan)
    if len(cells) == 0:
        return out if np.ndim(q) else out[0]
    order = _order_by_cell_then_value(cells, values)
    v = values[order].astype(np.float64)
    w = weights[order].astype(np.float64)
    count = np.bincount(cells, minlength=n_cells)
    end = np.cumsum(count)
    start = end - count
    cum = np.cumsum(w)
    before = np.concatenate([[0.0], cum])[start]  # total weight of the earlier cells
    within = cum - np.repeat(before, count)  # rises along each cell's run: weights > 0
    seen = np.flatnonzero(count)
    total = np.bincount(np.repeat(np.arange(n_cells), count), w, minlength=n_cells)[seen]
    first, stop = start[seen], end[seen]
    for k, qk in enumerate(qs):
        target = qk * total
        tol = 1e-9 * target
        # the first of each cell's run that reaches the target, by bisection on the runs
        # together: O(cells log run) instead of passes over every observation
        idx = _first_reaching(within, target - tol, first, stop)
        found = idx < stop
        idx, cell, at = idx[found], seen[found], np.flatnonzero(found)
        tie = (np.abs(within[idx] - target[at]) <= tol[at]) & (idx + 1 < stop[at])
        nxt = np.minimum(idx + 1, len(v) - 1)
        out[k, cell] = np.where(tie, 0.5 * (v[idx] + v[nxt]), v[idx])
    return out if np.ndim(q) else out[0]


def _first_reaching(
    rising: np.ndarray, floor: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """Per run ``lo[i]:hi[i]`` of the non-decreasing ``rising``, the first index whose
    value is at least ``floor[i]``; ``hi[i]`` where none is."""
    lo, hi = lo.copy(), hi.copy()
    while True:
        open_ = np.flatnonzero(lo < hi)
        if not len(open_):
            return lo
        mid = (lo[open_] + hi[open_]) // 2
        up = rising[mid] >= floor[open_]
        hi[open_[up]] = mid[up]
        lo[open_[~up]] = mid[~up] + 1


def _order_by_cell_then_value(cells: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Indices sorting by cell, then value, ties in their order (as ``np.lexsort``).

    One sort on a single key, faster than lexsort: for float32 values, the cell in the
    high 32 bits of a uint64 and the value's bits, made to sort as the value does, in
    the low 32; else the cell plus the value scaled into [0, 1) as a float64."""
    if len(cells) and values.dtype == np.float32 and 0 <= cells.min() and cells.max() < 2**32:
        # +0.0 turns -0.0 into 0.0: the two must tie, as lexsort has them
        bits = (values + np.float32(0.0)).view(np.uint32)
        negative = bits >= np.uint32(0x80000000)
        bits = np.where(negative, ~bits, bits | np.uint32(0x80000000))
        key = (cells.astype(np.uint64) << np.uint64(32)) | bits.astype(np.uint64)
        return np.argsort(key, kind="stable")
    v = values.astype(np.float64)
    lo, hi = v.min(), v.max()
    if cells.max() >= 2**30 or not np.isfinite(hi - lo):  # no resolution left: fall back
        return np.lexsort((values, cells))
    frac = (v - lo) / (hi - lo) * 0.999 if hi > lo else np.zeros_like(v)
    return np.argsort(cells.astype(np.float64) + frac, kind="stable")


def vector_median(
    cells: np.ndarray,
    vectors: np.ndarray,
    n_cells: int,
    *,
    n_projections: int = 8,
    seed: int = 0,
) -> np.ndarray:
    """Per cell, the observed vector closest to the median along random 1D projections.

    Tukey's idea: project the vectors onto random unit directions, take the median of
    each projection, and keep the observation whose projections deviate least (in the
    worst direction, scaled by the spread) from those medians. The result is always
    one of the observed vectors, so no new colours appear, and outliers (a car, a
    mis-projected facade) cannot pull it.

    Parameters
    ----------
    cells : (N,) int
    vectors : (N, k) array (for example RGB colours)
    n_cells : int
    n_projections : int
        Number of random directions.
    seed : int
        Seed of the directions.

    Returns
    -------
    (n_cells, k) array of the vectors' dtype; rows of empty cells are zero.
    """
    k = vectors.shape[1]
    out = np.zeros((n_cells, k), vectors.dtype)
    if len(cells) == 0:
        return out
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(n_projections, k))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    layout = CellLayout.of(cells, n_cells)
    ordered = vectors[layout.order]
    # one (P, N) array of projections, then of deviations, in place: a row at a time the
    # temporaries stay of one row's size (a tile's observations are millions)
    dev = np.empty((n_projections, len(cells)))
    for a in range(0, len(cells), CellLayout.BLOCK):
        dev[:, a : a + CellLayout.BLOCK] = (
            ordered[a : a + CellLayout.BLOCK].astype(float) @ dirs.T
        ).T
    for p, med in enumerate(layout.medians(dev)):
        np.abs(np.subtract(dev[p], layout.spread(med), out=dev[p]), out=dev[p])
    score = np.zeros(len(cells))
    for p, mad in enumerate(layout.medians(dev)):
        np.maximum(score, dev[p] / (layout.spread(mad) + 1e-6), out=score)
    # per cell the least score; among equal ones the first observation (exact, so that
    # near-ties do not depend on the tiling)
    has = layout.count > 0
    least = np.full(n_cells, np.inf)
    least[has] = np.minimum.reduceat(score, layout.start[has])
    c = layout.spread(np.arange(n_cells))  # each observation's cell, in layout order
    at = np.flatnonzero(score == layout.spread(least))
    first = at[np.r_[True, c[at][1:] != c[at][:-1]]]
    out[c[first]] = ordered[first]
    return out


def plane_residual_from_moments(cxx, cyy, cxy, cxz, cyz, czz) -> np.ndarray:
    """RMS residual of the least-squares plane z = a x + b y + c through a set of points,
    from their central second moments (arrays of one shape: one set per element), in the
    unit of z; where x and y are degenerate (collinear), the spread of z.

    The variance of z less what the best plane explains, which is
    ``c_z^T C_xy^-1 c_z`` for ``C_xy`` the 2 x 2 moments of x, y and ``c_z`` their
    moments with z.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        det = cxx * cyy - cxy * cxy
        explained = (cyy * cxz * cxz - 2 * cxy * cxz * cyz + cxx * cyz * cyz) / det
        return np.sqrt(np.maximum(czz - np.where(det > 1e-9, explained, 0.0), 0.0))

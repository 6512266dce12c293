"""Classes that stop at the fused grid's edges: a contrast-sensitive Potts model on the
cells (not in the super-pixel paper, which refines the classes on super-pixels later).

The per-view forest describes a pixel by its 11 x 11 patch, so near a boundary both sides
look alike and the accumulated confidences blur across it: on the tuning seeds, a rim of
ground one or two cells wide around every lawn came out as grass. The ortho's colour and
the DSM are sharp there. Each cell takes the label minimising

    E(c) = sum_i -log p_i(c_i) + omega sum_(i,j) w_ij [c_i != c_j],
    w_ij = exp(-beta_c |Lab_i - Lab_j|^2 - beta_h (h_i - h_j)^2) / d_ij

over 8-neighbours at distance d_ij (Boykov and Jolly 2001), with beta = 1 / (2 <.>), the
mean over the grid's pairs as in GrabCut (Rother et al. 2004): a change of class is cheap
where the colour or the height changes more than is usual in this grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.engine import Engine, ThreadEngine
from workbench.graph_cuts import alpha_expansion, grid_pairs, squared_differences
from workbench.raster import class_codes
from workbench.texture_seams import rgb_to_lab

PROB_FLOOR = 1e-4  # -log(1e-4) = 9.2: a confident cell flips only against strong edges
TILE = 256  # cells per tile side: on seed 0 the same labels as 512, and 1.6x faster
MARGIN = 32  # cells of context around each tile: labels settle within a few cells


def contrast_terms(ortho: np.ndarray, dsm: np.ndarray, pairs: np.ndarray) -> tuple:
    """Squared colour (CIELab) and height differences of neighbour pairs.

    Parameters
    ----------
    ortho : (H, W, 3) uint8
    dsm : (H, W) float, metres; NaN unknown
    pairs : (E, 2) int, flat indices

    Returns
    -------
    dc2, dh2 : (E,) float64; a pair with an unknown height has NaN ``dh2``.
    """
    dc2 = squared_differences(rgb_to_lab(ortho).reshape(-1, 3), pairs)
    return dc2, squared_differences(np.ravel(dsm), pairs)


def contrast_betas(
    ortho: np.ndarray, dsm: np.ndarray, seen: np.ndarray, band: int = TILE
) -> tuple[float, float]:
    """beta_c, beta_h: 1 / (2 mean) of the squared differences over every pair of seen
    8-neighbours of the grid, so that the weights do not depend on how it is tiled.
    Summed in bands of ``band`` rows (with the next band's first row), one neighbour
    direction at a time on shifted views: memory stays a few bands whatever the grid."""
    H, W = seen.shape
    sums = np.zeros(4)  # colour sum, pairs; height sum, pairs with both heights known
    for r0 in range(0, H, band):
        own, r1 = min(band, H - r0), min(r0 + band + 1, H)  # pairs from the band's rows
        lab, seen_band = rgb_to_lab(ortho[r0:r1]), seen[r0:r1]
        z = np.asarray(dsm[r0:r1], np.float64)
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
            rows = min(own, r1 - r0 - dr)
            a = (slice(0, rows), slice(max(-dc, 0), W - max(dc, 0)))
            b = (slice(dr, dr + rows), slice(max(dc, 0), W - max(-dc, 0)))
            both = seen_band[a] & seen_band[b]
            dc2 = np.sum((lab[a] - lab[b]) ** 2, axis=-1, dtype=np.float64)[both]
            dh2 = ((z[a] - z[b]) ** 2)[both]
            known = np.isfinite(dh2)
            sums += (dc2.sum(), dc2.size, dh2[known].sum(), known.sum())
    mc = sums[0] / sums[1] if sums[1] else 0.0
    mh = sums[2] / sums[3] if sums[3] else 0.0
    return 1.0 / (2.0 * max(mc, 1e-12)), 1.0 / (2.0 * max(mh, 1e-12))


@dataclass(frozen=True)
class CrfWeights:
    """What every tile's task shares: the pairwise weight, the contrasts' betas (the
    whole grid's, so that the weights do not depend on the tiling) and the sweeps."""

    omega: float
    beta_c: float
    beta_h: float
    max_sweeps: int


def contrast_class_crf(
    class_prob: np.ndarray,
    ortho: np.ndarray,
    dsm: np.ndarray,
    omega: float,
    tile: int = TILE,
    max_sweeps: int = 3,
    engine: Engine | None = None,
) -> np.ndarray:
    """Class codes of the contrast-sensitive Potts model, tile by tile.

    Parameters
    ----------
    class_prob : (4, H, W) float
        Accumulated class confidences (ground, grass, tree, building), NaN where unseen.
    ortho : (H, W, 3) uint8
    dsm : (H, W) float, metres
    omega : float
        Weight of the pairwise term; 0 gives the most probable class of each cell.
    tile : int
        Cells per tile side; each tile is solved with ``MARGIN`` cells of context around
        it, so memory is that of a tile whatever the grid.
    max_sweeps : int
        Alpha-expansion sweeps.
    engine : Engine, optional
        Runs the tiles as the tasks of a stage ``class_crf`` (:mod:`workbench.engine`);
        by default one after another in this process. The labels do not depend on it.

    Returns
    -------
    (H, W) uint8 codes 1-4, 0 where unseen.
    """
    codes = class_codes(class_prob)
    seen = codes > 0
    if omega <= 0 or not seen.any():
        return codes
    beta_c, beta_h = contrast_betas(ortho, dsm, seen)
    weights = CrfWeights(omega, beta_c, beta_h, max_sweeps)
    H, W = seen.shape
    corners = [(r0, c0) for r0 in range(0, H, tile) for c0 in range(0, W, tile)]
    # each task takes its tile's window along: no worker holds the whole grid
    items = [tile_window(corner, tile, class_prob, ortho, dsm, seen) for corner in corners]
    engine = engine or ThreadEngine(1)
    labels = engine.map(crf_tile, items, weights, stage="class_crf")
    for (r0, c0), core in zip(corners, labels, strict=True):
        codes[r0 : r0 + core.shape[0], c0 : c0 + core.shape[1]] = core
    return codes


def tile_window(corner: tuple[int, int], tile: int, class_prob, ortho, dsm, seen) -> tuple:
    """The tile whose first cell is ``corner`` with ``MARGIN`` cells of context on every
    side: its (rows, columns) in the window, and the window of each raster (views)."""
    r0, c0 = corner
    H, W = seen.shape
    rs = slice(max(r0 - MARGIN, 0), min(r0 + tile + MARGIN, H))
    cs = slice(max(c0 - MARGIN, 0), min(c0 + tile + MARGIN, W))
    core = (slice(r0 - rs.start, r0 - rs.start + min(tile, H - r0)),
            slice(c0 - cs.start, c0 - cs.start + min(tile, W - c0)))  # fmt: skip
    return core, class_prob[:, rs, cs], ortho[rs, cs], dsm[rs, cs], seen[rs, cs]


def crf_tile(item: tuple, how: CrfWeights) -> np.ndarray:
    """Task: the labels (uint8 codes, 0 unseen) of one tile (:func:`tile_window`),
    solved on its window."""
    core, prob, ortho, dsm, seen = item
    labels = _solve(prob, ortho, dsm, seen, how.omega, how.beta_c, how.beta_h, how.max_sweeps)
    return labels[core]


def _solve(prob, ortho, dsm, seen, omega, beta_c, beta_h, max_sweeps) -> np.ndarray:
    """(h, w) uint8 codes of one window (0 unseen)."""
    pairs, length = grid_pairs(seen.shape, diagonals=True)
    flat_seen = seen.ravel()
    both = flat_seen[pairs[:, 0]] & flat_seen[pairs[:, 1]]
    pairs, length = pairs[both], length[both]
    dc2, dh2 = contrast_terms(ortho, dsm, pairs)
    # an unknown height on either side: colour alone decides
    weights = np.exp(-beta_c * dc2 - beta_h * np.nan_to_num(dh2, nan=0.0)) / length
    nodes = np.flatnonzero(flat_seen)
    local = np.full(flat_seen.size, -1)
    local[nodes] = np.arange(len(nodes))
    p = prob.reshape(len(prob), -1)[:, nodes].T
    unary = -np.log(np.clip(p, PROB_FLOOR, 1.0))
    labels = alpha_expansion(unary, local[pairs], weights, omega, max_sweeps=max_sweeps)
    out = np.zeros(flat_seen.size, np.uint8)
    out[nodes] = labels + 1
    return out.reshape(seen.shape)

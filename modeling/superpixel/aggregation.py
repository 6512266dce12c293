"""Aggregation over super-pixels and their adjacency graph (the super-pixel paper, 4.1-4.2)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from workbench.robust import group_median, plane_residual_from_moments

# the fusion's class map's share of a cell's likelihoods: on seeds 0-2 and 6-10 the class
# CRF's accuracy, footprint quality and height RMSE were flat from 0.25 to 1, and far
# from 0 (the probabilities alone); an even mixture of the two experts
LABEL_SHARE = 0.5


@dataclass
class SuperpixelGraph:
    """Super-pixels with what the CRFs need.

    Attributes
    ----------
    labels : (H, W) int64
        Super-pixel of every cell, 0..N-1.
    count : (N,) int64
        Cells per super-pixel.
    class_sum : (N, C) float64
        Summed class probabilities (cells without any get 1/C each).
    colour : (N, 3) float64
        Mean CIELab colour (L 0-100).
    height_median : (N,) float64
        Median DSM height, NaN where no cell has one.
    plane_residual : (N,) float64 or None
        RMS residual of the least-squares plane through its DSM cells, metres: a roof
        face is planar, a crown lumpy (NaN under 6 known cells). None unless asked for
        (only the class CRF's geometric unary reads it).
    edges : (E, 2) int64
        Adjacent super-pixel pairs, i < j.
    boundary : (E,) float64
        b: number of 4-neighbour cell pairs across the shared boundary.
    colour_distance : (E,) float64
        g: L2 distance of the two mean Lab colours.
    """

    labels: np.ndarray
    count: np.ndarray
    class_sum: np.ndarray
    colour: np.ndarray
    height_median: np.ndarray
    plane_residual: np.ndarray | None
    edges: np.ndarray
    boundary: np.ndarray
    colour_distance: np.ndarray

    @property
    def n(self) -> int:
        return len(self.count)

    @property
    def pairwise(self) -> np.ndarray:
        """V of eq. 3 for differing labels: b / (1 + g), (E,)."""
        return self.boundary / (1.0 + self.colour_distance)


def superpixel_graph(
    labels: np.ndarray,
    rgb: np.ndarray,
    class_prob: np.ndarray,
    dsm: np.ndarray,
    residuals: bool = True,
    classes: np.ndarray | None = None,
) -> SuperpixelGraph:
    """Aggregate the fused rasters over super-pixels and build their adjacency graph.

    Parameters
    ----------
    labels : (H, W) int
        Super-pixels 0..N-1.
    rgb : (H, W, 3) uint8
    class_prob : (C, H, W) float
        Class probabilities; cells whose probabilities are NaN or sum to 0 count as uniform.
    dsm : (H, W) float
        Metres, NaN unknown.
    residuals : bool
        Fit each super-pixel's plane (``plane_residual``): on a city, its moments are
        the largest arrays of the aggregation.
    classes : (H, W) uint8, optional
        The fusion's class map (codes 1..C, 0 unseen). Each seen cell's likelihoods are
        then ``LABEL_SHARE`` of its class as a certainty and the rest its probabilities
        (ours, not the paper's): the map holds what the probabilities do not, the
        fusion's CRF across cells and its planar objects, a roof's shaded hip that the
        forest gave to tree at 0.6-0.74 and the map to building.
    """
    n = int(labels.max()) + 1
    flat = labels.ravel()
    count = np.bincount(flat, minlength=n)
    C = class_prob.shape[0]
    # one class at a time, not a float64 copy of all (some 64 bytes a cell); confidences
    # are not negative, so a cell whose sum is 0 is one with none above 0
    empty = ~(class_prob.reshape(C, -1) > 0).any(axis=0)
    class_sum = np.zeros((n, C))
    if classes is not None:
        seen = classes.ravel() > 0
        seen_class = classes.ravel()[seen]
    for c in range(C):
        p = np.nan_to_num(class_prob[c].ravel().astype(np.float64), nan=0.0, copy=False)
        p[empty] = 1.0 / C
        if classes is not None:
            p[seen] = (1.0 - LABEL_SHARE) * p[seen] + LABEL_SHARE * (seen_class == c + 1)
        class_sum[:, c] = np.bincount(flat, weights=p, minlength=n)
    scaled = rgb.astype(np.float32)
    scaled /= 255.0
    lab = cv2.cvtColor(scaled, cv2.COLOR_RGB2Lab).reshape(-1, 3)
    colour = np.stack([np.bincount(flat, weights=lab[:, k], minlength=n) for k in range(3)], 1)
    colour /= np.maximum(count, 1)[:, None]
    known = np.isfinite(dsm.ravel())
    height_median = group_median(flat[known], dsm.ravel()[known], n)
    keys = []
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1, :], labels[1:, :])):
        diff = a != b
        lo, hi = np.minimum(a[diff], b[diff]), np.maximum(a[diff], b[diff])
        keys.append(lo.astype(np.int64) * n + hi)  # sorts as the pairs (lo, hi) do
    key, boundary = np.unique(np.concatenate(keys), return_counts=True)
    edges = np.stack([key // n, key % n], axis=1)
    g = np.linalg.norm(colour[edges[:, 0]] - colour[edges[:, 1]], axis=1)
    return SuperpixelGraph(
        labels, count, class_sum, colour, height_median,
        plane_residuals(labels, dsm, n) if residuals else None, edges,
        boundary.astype(np.float64), g,
    )  # fmt: skip


def plane_residuals(labels: np.ndarray, dsm: np.ndarray, n: int) -> np.ndarray:
    """(n,) RMS residual of the least-squares plane z = a x + b y + c through the known
    DSM cells of each super-pixel, metres (x, y in cells: the residual is in metres
    whatever their unit); NaN under 6 known cells. From per-super-pixel sums of the
    moments, one pass over the grid."""
    known = np.isfinite(dsm)
    rows, cols = np.nonzero(known)  # in the order of the mask's cells
    sp = labels[known]
    z = dsm[known].astype(np.float64)
    x, y = cols.astype(np.float64), rows.astype(np.float64)
    k = np.bincount(sp, minlength=n).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        for a in (x, y, z):  # centred per super-pixel, in place (the city's were 150 MiB)
            a -= (np.bincount(sp, a, n) / k)[sp]
        moments = (
            np.bincount(sp, a * b, n) / k
            for a, b in ((x, x), (y, y), (x, y), (x, z), (y, z), (z, z))
        )
        rms = plane_residual_from_moments(*moments)
    return np.where(k >= 6, rms, np.nan)

"""Classes of LiDAR returns that carry none, from what LiDAR carries: geometry and echoes.

A survey leaves vegetation and much else unclassified (ASPRS 1; a PLY has no classes at
all). Those returns are classed here from their own cloud, not from colours learnt on the
synthetic city:

* height above the ground (the DTM): below ``low_m`` a return is ground (grass where the
  cloud has colour and it is green);
* above it, the shape of its neighbourhood at a few sizes (the eigenvalues of the local 3D
  covariance, Weinmann et al. 2015: linearity, planarity, scattering, and the verticality
  of the normal), and its echoes: a roof or a wall is a plane that returns one echo per
  pulse, a crown is a scatter of points that splits pulses into several. Elevated returns
  whose neighbourhood is planar and, where the cloud records echoes, mostly single-echo
  are building; the rest tree.

All lengths are metres; callers convert from the CRS's units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ASPRS_GROUND, ASPRS_LOW_VEGETATION, ASPRS_HIGH_VEGETATION, ASPRS_BUILDING = 2, 3, 5, 6
UNCLASSIFIED = (0, 1)
SCALES = (10, 25, 50)  # neighbours in each neighbourhood


@dataclass
class ShapeFeatures:
    """Covariance features of each return's neighbourhood, one column per scale.

    Attributes (each (N, S) float, in [0, 1])
    ----------
    linearity : (l1 - l2) / l1
    planarity : (l2 - l3) / l1
    scattering : l3 / l1
    verticality : 1 - |n_z| of the normal (the smallest eigenvector): 0 flat, 1 a wall
    """

    linearity: np.ndarray
    planarity: np.ndarray
    scattering: np.ndarray
    verticality: np.ndarray


def nearest_returns(xyz: np.ndarray, at: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest returns of each return ``at`` (M,) among ``xyz`` (N, 3), itself
    first (scipy's k-d tree): (M, k) indices into ``xyz``, and ``xyz`` in a local origin."""
    from scipy.spatial import cKDTree

    local = xyz - xyz.min(axis=0)
    _, nbrs = cKDTree(local).query(local[at], k=min(k, len(local)), workers=-1)
    return nbrs.reshape(len(at), -1), local


def shape_features(
    points: np.ndarray, nbrs: np.ndarray, scales=SCALES, chunk: int = 200_000
) -> ShapeFeatures:
    """Covariance features of each row of neighbours ``nbrs`` (M, K) of ``points`` (N, 3)
    at each number of (nearest) neighbours in ``scales``, K at most."""
    out = {name: np.zeros((len(nbrs), len(scales))) for name in ShapeFeatures.__annotations__}
    for s in range(0, len(nbrs), chunk):
        rows = slice(s, s + chunk)
        for j, k in enumerate(scales):
            pts = points[nbrs[rows, :k]]  # (m, k, 3)
            centred = pts - pts.mean(axis=1, keepdims=True)
            cov = np.einsum("mki,mkj->mij", centred, centred) / pts.shape[1]
            values, vectors = np.linalg.eigh(cov)  # ascending
            l3, l2, l1 = (np.maximum(values[:, i], 0.0) for i in range(3))
            l1 = np.where(l1 > 0, l1, 1.0)
            out["linearity"][rows, j] = (l1 - l2) / l1
            out["planarity"][rows, j] = (l2 - l3) / l1
            out["scattering"][rows, j] = l3 / l1
            out["verticality"][rows, j] = 1.0 - np.abs(vectors[:, 2, 0])
    return ShapeFeatures(**out)


def multi_echo_share(number_of_returns: np.ndarray, nbrs: np.ndarray, k: int = 25) -> np.ndarray:
    """(M,) share of the ``k`` nearest returns (rows of ``nbrs``, nearest first) that came
    from a pulse split into several echoes."""
    return (number_of_returns[nbrs[:, :k]] > 1).mean(axis=1)


LOW_M = 2.0  # returns lower than this above the ground are ground or grass
SURFACE_SCATTERING = 0.08  # l3 / l1 below this: the neighbourhood is a surface
MULTI_ECHO_SHARE = 0.5  # more neighbours than this from split pulses: vegetation
GREEN_EXG = 0.05  # excess green 2g - r - b (chromatic coordinates) above this: grass


def classify_returns(
    xyz: np.ndarray,
    height_above_ground: np.ndarray,
    todo: np.ndarray,
    *,
    number_of_returns: np.ndarray | None = None,
    rgb: np.ndarray | None = None,
    low: float = LOW_M,
) -> np.ndarray:
    """ASPRS codes for the returns ``todo`` (M,) of ``xyz`` (N, 3), from geometry and echoes.

    Parameters
    ----------
    height_above_ground : (N,) float
        In the units of ``xyz`` (NaN where unknown: those stay ground).
    number_of_returns : (N,) int, optional
        Echoes of each return's pulse; without them the shape alone decides.
    rgb : (N, 3) uint8, optional
        Colour, only to tell grass from bare ground among the low returns.
    low : float
        ``LOW_M`` in the units of ``xyz``.

    Returns
    -------
    (M,) uint8 ASPRS codes: 2 ground, 3 low vegetation (grass), 5 high vegetation (tree),
    6 building.
    """
    codes = np.full(len(todo), ASPRS_GROUND, np.uint8)
    hag = height_above_ground[todo]
    if rgb is not None:
        c = rgb[todo].astype(np.float64)
        total = np.maximum(c.sum(axis=1), 1.0)
        exg = (2 * c[:, 1] - c[:, 0] - c[:, 2]) / total
        codes[~(hag >= low) & (exg > GREEN_EXG)] = ASPRS_LOW_VEGETATION
    up = np.flatnonzero(hag >= low)
    if len(up) == 0:
        return codes
    # one neighbour query serves every scale and the echoes
    nbrs, local = nearest_returns(xyz, todo[up], max(SCALES))
    surface = np.median(shape_features(local, nbrs).scattering, axis=1) < SURFACE_SCATTERING
    if number_of_returns is not None:
        surface &= multi_echo_share(number_of_returns, nbrs) < MULTI_ECHO_SHARE
    codes[up] = np.where(surface, ASPRS_BUILDING, ASPRS_HIGH_VEGETATION)
    return codes

"""Segmentation (the variational paper, eq. 1, with eq. 8's pull towards the priors): a
level set over the ortho's colour and the DSM's height with Gaussian region terms.

phi > 0 marks buildings. Each source A (colour, height, and the fusion's building
probability beside them) adds r_obj(A) - r_bg(A) to the force on the boundary, where
r(A) = (A - mu)^T Sigma^-1 (A - mu) + log det Sigma is the negative log-likelihood of A
under the Gaussian of the cells inside (object) or outside (background), re-estimated
as the boundary moves. The boundary's length keeps it smooth; with registered priors
(eq. 8) a third force pulls phi towards them.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

_EPS_CELLS = 1.5  # width of the smoothed Heaviside and Dirac, cells
_BAND_CELLS = 8.0  # phi is kept a signed distance clipped to this many cells
_REINIT_EVERY = 10  # steps between re-initialisations and re-estimated statistics
_MIN_VARIANCE = 1e-4  # floor of each source's variance (units of the source squared)
_BAND_ROWS = 256  # rows of a band of the descent step
_CHUNK_CELLS = 1 << 18  # cells of a chunk of the region terms


def heaviside(phi: np.ndarray, eps: float = _EPS_CELLS) -> np.ndarray:
    """H_eps(phi) = 1/2 (1 + 2/pi arctan(phi / eps)): eq. 1's smoothed step."""
    return 0.5 + np.arctan(phi / eps) / np.pi


def dirac(phi: np.ndarray, eps: float = _EPS_CELLS) -> np.ndarray:
    """delta_eps = H_eps'."""
    return (eps / np.pi) / (eps**2 + phi**2)


def gaussian_cost(values: np.ndarray, sample: np.ndarray, chunk: int = _CHUNK_CELLS) -> np.ndarray:
    """Negative log-likelihood (up to a constant) of ``values`` under the Gaussian fitted
    to ``sample``: (A - mu)^T Sigma^-1 (A - mu) + log det Sigma.

    values : (N, C) float; sample : (M, C) float, M >= 2; chunk : cells taken at once.
    Returns (N,) float.
    """
    mu = sample.mean(axis=0)
    cov = np.atleast_2d(np.cov(sample, rowvar=False)) + _MIN_VARIANCE * np.eye(sample.shape[1])
    inv = np.linalg.inv(cov)
    q = np.empty(len(values))
    # in chunks of cells: a city's differences and terms were some 50 bytes a cell;
    # the quadratic form channel pair by channel pair: C is at most 3, and einsum or
    # matmul over a tiny inner axis are several times slower on millions of cells
    for start in range(0, len(values), chunk):
        d = values[start : start + chunk] - mu
        part = np.zeros(len(d))
        for a in range(d.shape[1]):
            part += inv[a, a] * d[:, a] ** 2
            for b in range(a + 1, d.shape[1]):
                part += 2.0 * inv[a, b] * d[:, a] * d[:, b]
        q[start : start + len(d)] = part
    return q + np.log(np.linalg.det(cov))


def region_force(
    sources: list[tuple[np.ndarray, np.ndarray, float]], inside: np.ndarray
) -> np.ndarray:
    """sum over sources of w (r_obj - r_bg): positive where a cell looks like background.

    Parameters
    ----------
    sources : list of (values (H, W, C) float, valid (H, W) bool, weight)
    inside : (H, W) bool
        The current object region.

    Returns
    -------
    (H, W) float, 0 where no source is valid.
    """
    return _region_force(_valid_values(sources), inside)


def _valid_values(sources: list) -> list:
    """Each source as (its valid cells' values (N, C), valid, weight): gathered once,
    since the level set re-estimates its statistics many times on the same values."""
    return [(values[valid], valid, weight) for values, valid, weight in sources if weight]


def _region_force(gathered: list, inside: np.ndarray) -> np.ndarray:
    force = np.zeros(inside.shape)
    for v, valid, weight in gathered:
        obj = inside[valid]
        if obj.sum() < 2 or (~obj).sum() < 2:
            continue
        force[valid] += weight * (gaussian_cost(v, v[obj]) - gaussian_cost(v, v[~obj]))
    return force


def signed_distance(inside: np.ndarray) -> np.ndarray:
    """(H, W) distance to the boundary in cells, positive inside, clipped to the band."""
    d = ndimage.distance_transform_edt(inside) - ndimage.distance_transform_edt(~inside)
    return np.clip(d, -_BAND_CELLS, _BAND_CELLS)


def curvature(phi: np.ndarray) -> np.ndarray:
    """div(grad phi / |grad phi|), 1 / cells."""
    gy, gx = np.gradient(phi)
    norm = np.sqrt(gx**2 + gy**2) + 1e-8
    return np.gradient(gx / norm, axis=1) + np.gradient(gy / norm, axis=0)


def level_set_segmentation(
    sources: list[tuple[np.ndarray, np.ndarray, float]],
    init: np.ndarray,
    *,
    length_weight: float,
    iterations: int,
    prior: np.ndarray | None = None,
    prior_weight: np.ndarray | float = 0.0,
) -> np.ndarray:
    """Evolve phi by gradient descent on eq. 1 (+ eq. 8's prior term) from ``init``.

    Parameters
    ----------
    sources : list of (values (H, W, C), valid (H, W) bool, weight)
        Colour, height, ...: each a region term with its weight (eq. 1's varrho).
    init : (H, W) bool
        The initial object region (the fusion's building probability, or footprints).
    length_weight : float
        Weight of the boundary length, per cell of curvature.
    iterations : int
    prior : (H, W) float in [0, 1], optional
        H_eps(phi~_i(T_i(x))) of the registered priors (eq. 8).
    prior_weight : float or (H, W) float
        mu / sigma_i^2 where a prior is enforced (x_i(L) > 0), 0 elsewhere.

    Returns
    -------
    (H, W) bool: phi > 0.
    """
    gathered = _valid_values(sources)
    phi = signed_distance(init)
    force = _region_force(gathered, phi > 0)
    for it in range(iterations):
        if it and it % _REINIT_EVERY == 0:
            phi = signed_distance(phi > 0)
            force = _region_force(gathered, phi > 0)
        step = descent_step(phi, force, length_weight, prior, prior_weight)
        top = max(step.max(), -step.min())
        if top == 0:
            break
        step *= min(1.0, 0.5 / top)  # at most half a cell per step
        phi += step
    return phi > 0


def descent_step(
    phi: np.ndarray,
    force: np.ndarray,
    length_weight: float,
    prior: np.ndarray | None = None,
    prior_weight: np.ndarray | float = 0.0,
    rows: int = _BAND_ROWS,
) -> np.ndarray:
    """(H, W) dphi/dt of eq. 1 (+ eq. 8): delta_eps(phi) (length_weight kappa - force
    - 2 prior_weight (H_eps(phi) - prior)), in bands of ``rows`` rows.

    The curvature's second differences reach two rows: each band is computed with two
    rows of the next ones about it, so the step is the whole grid's, bit for bit, with
    a band's temporaries (some 80 bytes a cell in float64) rather than the grid's.
    """
    H = phi.shape[0]
    step = np.empty_like(phi, dtype=np.float64)
    for r0 in range(0, H, rows):
        r1 = min(r0 + rows, H)
        a, b = max(r0 - 2, 0), min(r1 + 2, H)
        p = phi[r0:r1]
        speed = length_weight * curvature(phi[a:b])[r0 - a : r1 - a] - force[r0:r1]
        if prior is not None:
            weight = prior_weight[r0:r1] if np.ndim(prior_weight) else prior_weight
            speed = speed - 2.0 * weight * (heaviside(p) - prior[r0:r1])
        step[r0:r1] = dirac(p) * speed
    return step

"""The energy of a configuration of blocks (the DEM-blocks paper, section 3.2):
U(x) = sum_i Gamma_i(S_{x_i}, D_i) + beta * sum_{i~j} 1{x_i ~a x_j} g(x_i, x_j).

- the likelihood (eq. 2-3): per support the L-alpha distance between the block's roof
  and the DSM over the support's cells;
- the prior (eq. 4-5): neighbouring blocks that are "joinable" (same roof form,
  compatible orientations, no height step on their common edge) earn between 0 and
  -beta, the more the closer their parameters.
"""

from __future__ import annotations

import numpy as np

from .library import Block, orientation_free

#: metres: gutters or ridges further apart than this across a common edge are a step
#: (condition 3 of "joinable"), not one roof
STEP_M = 1.0
_PERPENDICULAR_COS = np.cos(np.radians(70.0))  # a ridge this close to square to the edge


def likelihood(model: np.ndarray, dsm: np.ndarray, alpha: float) -> float:
    """Eq. 3: Gamma = (sum_s |S_x(s) - Lambda(s)|^alpha)^(1 / alpha).

    model, dsm : (n,) heights at the support's cells, metres (the DSM has no NaN here)."""
    return float(np.sum(np.abs(model - dsm) ** alpha) ** (1.0 / alpha))


def joinable(a: Block, b: Block, ridge_a: np.ndarray, ridge_b: np.ndarray,
             edge: np.ndarray) -> bool:  # fmt: skip
    """The paper's assembly law x_i ~a x_j: the same roof form; orientations that can
    join (a ridge running into the common edge, or a form with no ridge direction);
    no roof height discontinuity on the common edge (gutters and ridges within
    :data:`STEP_M`).

    ridge_a, ridge_b : (2,) world unit vectors of the ridges; edge : (2,) unit vector of
    the common edge."""
    if a.form != b.form:
        return False
    if not orientation_free(a.form):
        into = [abs(float(r @ edge)) < _PERPENDICULAR_COS for r in (ridge_a, ridge_b)]
        if not any(into):  # both ridges along the edge: two roofs side by side, a valley
            return False
    return abs(a.gutter - b.gutter) <= STEP_M and abs(a.top - b.top) <= STEP_M


def parameter_distance(a: Block, b: Block, d_max: float) -> float:
    """Eq. 5: g = D / D_max - 1 in [-1, 0], D the sum of the parameters' absolute
    differences (all metres: the weights omega_k are 1), D_max the largest D the
    parameters' ranges allow."""
    d = float(np.sum(np.abs(np.subtract(a.params, b.params))))
    return min(d / max(d_max, 1e-9), 1.0) - 1.0


def pair_energy(a: Block, b: Block, ridge_a, ridge_b, edge, d_max: float, beta: float) -> float:
    """Eq. 4's term of one neighbouring pair: beta g(x_i, x_j) if they are joinable,
    else 0."""
    if not joinable(a, b, ridge_a, ridge_b, edge):
        return 0.0
    return beta * parameter_distance(a, b, d_max)


def max_distance(ranges_a: np.ndarray, ranges_b: np.ndarray) -> float:
    """D_max of a pair for one form: the sum of the widest of their parameter ranges."""
    wa = ranges_a[:, 1] - ranges_a[:, 0]
    wb = ranges_b[:, 1] - ranges_b[:, 0]
    return float(np.sum(np.maximum(wa, wb)))

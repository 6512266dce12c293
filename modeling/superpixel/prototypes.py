"""Roof prototypes: affinity propagation on plane hypotheses (the super-pixel paper, 5.2)."""

from __future__ import annotations

import warnings

import numpy as np
from sklearn.cluster import AffinityPropagation
from sklearn.exceptions import ConvergenceWarning

from modeling.shared.planes import point_plane_distances

from .options import SuperpixelOptions


def hypothesis_similarity(
    planes: np.ndarray,
    points: list[np.ndarray],
    owner: np.ndarray,
    adjacency: dict[int, list[int]],
) -> np.ndarray:
    """Sparse similarity of plane hypotheses for affinity propagation.

    s(i, k) = - mean distance of the points of hypothesis i's super-pixel to plane k, for
    k on the same or an adjacent super-pixel; every other pair gets a similarity far below
    any computed one, so it never chooses an exemplar (the paper computes it sparsely).

    Parameters
    ----------
    planes : (K, 4)
        Hypotheses.
    points : list of (N_i, 3)
        Points each hypothesis was fitted to.
    owner : (K,) int
        Super-pixel of each hypothesis.
    adjacency : {super-pixel: adjacent super-pixels}
    """
    K = len(planes)
    S = np.full((K, K), np.nan)
    index = {int(o): k for k, o in enumerate(owner)}
    near = np.eye(K, dtype=bool)
    for a, i in index.items():
        for b in adjacency.get(a, ()):
            if b in index:
                near[i, index[b]] = True
    for i in range(K):
        d = point_plane_distances(planes, points[i])  # (N_i, K)
        S[i, near[i]] = -d[:, near[i]].mean(axis=0)
    floor = np.nanmin(S) - 100.0 if np.isfinite(S).any() else -100.0
    return np.where(np.isnan(S), floor, S)


def cluster_prototypes(
    similarity: np.ndarray, preference: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Affinity propagation (scikit-learn) on a precomputed similarity.

    Parameters
    ----------
    similarity : (K, K) float
    preference : float
        Self-similarity: how readily a hypothesis becomes its own exemplar. With
        similarities of minus a mean distance in metres, -0.25 lets a hypothesis stand
        alone unless another explains its points within about 25 cm.

    Returns
    -------
    exemplars : (P,) int indices of the chosen hypotheses
    assignment : (K,) int index into ``exemplars`` of each hypothesis
    """
    K = len(similarity)
    if K == 1:
        return np.array([0]), np.array([0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        warnings.simplefilter("ignore", UserWarning)  # "equal similarities": one prototype
        ap = AffinityPropagation(
            affinity="precomputed",
            preference=preference,
            damping=0.7,
            max_iter=400,
            random_state=seed,
        ).fit(similarity)
    exemplars = np.asarray(ap.cluster_centers_indices_, np.int64)
    if len(exemplars) == 0:  # not converged: every hypothesis its own prototype
        return np.arange(K), np.arange(K)
    return exemplars, np.asarray(ap.labels_, np.int64)


def roof_prototypes(
    hypotheses: dict[int, tuple[np.ndarray, np.ndarray]],
    adjacency: dict[int, list[int]],
    options: SuperpixelOptions,
) -> np.ndarray:
    """Cluster the hypotheses (from :func:`plane_hypotheses`) into prototypes by affinity
    propagation (section 5.2).

    Returns
    -------
    (P, 4) prototype planes.
    """
    owners = np.array(list(hypotheses))
    planes = np.array([hypotheses[i][0] for i in owners])
    support = [hypotheses[i][1] for i in owners]
    S = hypothesis_similarity(planes, support, owners, adjacency)
    exemplars, _ = cluster_prototypes(S, -options.prototype_tolerance_m, options.seed)
    return planes[exemplars]

"""Roof prototypes: affinity propagation on plane hypotheses (the super-pixel paper, 5.2)."""

from __future__ import annotations

import numpy as np

from modeling.shared.affinity_propagation import sparse_affinity_propagation
from workbench.planes import point_plane_distances

from .options import SuperpixelOptions


def hypothesis_similarity(
    planes: np.ndarray,
    points: list[np.ndarray],
    owner: np.ndarray,
    adjacency: dict[int, list[int]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sparse similarity of plane hypotheses for affinity propagation.

    s(i, k) = - mean distance of the points of hypothesis i's super-pixel to plane k, for
    k on the same or an adjacent super-pixel only, as the paper computes it: a building of
    K hypotheses has O(K) pairs, not K^2.

    Parameters
    ----------
    planes : (K, 4)
        Hypotheses.
    points : list of (N_i, 3)
        Points each hypothesis was fitted to.
    owner : (K,) int
        Super-pixel of each hypothesis.
    adjacency : {super-pixel: adjacent super-pixels}

    Returns
    -------
    rows, cols : (E,) int
        Pairs (i, k) of hypotheses, i != k.
    similarity : (E,) float
        s(i, k), minus metres.
    """
    index = {int(o): k for k, o in enumerate(owner)}
    rows, cols, sims = [], [], []
    for a, i in index.items():
        near = np.array([index[b] for b in adjacency.get(a, ()) if b in index], np.int64)
        if len(near):
            rows.append(np.full(len(near), i))
            cols.append(near)
            sims.append(-point_plane_distances(planes[near], points[i]).mean(axis=0))
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(sims)


def cluster_prototypes(
    similarity: tuple[np.ndarray, np.ndarray, np.ndarray],
    n: int,
    preference: float,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Affinity propagation on the sparse similarity of :func:`hypothesis_similarity`.

    Parameters
    ----------
    similarity : (rows, cols, s)
    n : int
        Number of hypotheses.
    preference : float
        Self-similarity: how readily a hypothesis becomes its own exemplar. With
        similarities of minus a mean distance in metres, -0.25 lets a hypothesis stand
        alone unless another explains its points within about 25 cm.

    Returns
    -------
    exemplars : (P,) int indices of the chosen hypotheses
    assignment : (K,) int index into ``exemplars`` of each hypothesis (-1: none adjacent)
    """
    if n == 1:
        return np.array([0]), np.array([0])
    exemplars, assignment = sparse_affinity_propagation(
        *similarity, n, preference, damping=0.7, max_iter=400, seed=seed
    )
    if len(exemplars) == 0:  # no exemplar at all: every hypothesis its own prototype
        return np.arange(n), np.arange(n)
    return exemplars, assignment


def roof_prototypes(
    hypotheses: dict[int, tuple[np.ndarray, np.ndarray]],
    adjacency: dict[int, list[int]],
    options: SuperpixelOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster the hypotheses (from :func:`plane_hypotheses`) into prototypes by affinity
    propagation (section 5.2).

    Returns
    -------
    planes : (P, 4) prototype planes
    anchors : (P,) int, the super-pixel of each prototype's exemplar hypothesis
    """
    owners = np.array(list(hypotheses))
    planes = np.array([hypotheses[i][0] for i in owners])
    support = [hypotheses[i][1] for i in owners]
    S = hypothesis_similarity(planes, support, owners, adjacency)
    exemplars, _ = cluster_prototypes(S, len(owners), -options.prototype_tolerance_m, options.seed)
    return planes[exemplars], owners[exemplars]

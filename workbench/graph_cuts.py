"""Conditional random fields on a graph: super-pixels' adjacency (the super-pixel paper,
eq. 2) or a grid's neighbours (:func:`grid_pairs`).

E(c) = sum_i D_i(c_i) + omega * sum_(i,j) w_ij [c_i != c_j], minimised with graph cuts
(PyMaxflow): one exact cut for two labels, alpha-expansion moves for more.
"""

from __future__ import annotations

import maxflow
import numpy as np


def grid_pairs(shape: tuple[int, int], diagonals: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Neighbour pairs of a row-major grid and the distance between their centres.

    Parameters
    ----------
    shape : (H, W)
    diagonals : bool
        8-neighbours instead of 4.

    Returns
    -------
    pairs : (E, 2) int
        Flat indices, right and down neighbours first, then the two diagonals.
    length : (E,) float
        1 or sqrt(2), in cells.
    """
    H, W = shape
    idx = np.arange(H * W).reshape(H, W)
    steps = [(idx[:, :-1], idx[:, 1:]), (idx[:-1], idx[1:])]
    if diagonals:
        steps += [(idx[:-1, :-1], idx[1:, 1:]), (idx[:-1, 1:], idx[1:, :-1])]
    pairs = [np.column_stack([a.ravel(), b.ravel()]) for a, b in steps]
    length = [np.full(len(p), 1.0 if k < 2 else np.sqrt(2.0)) for k, p in enumerate(pairs)]
    return np.concatenate(pairs), np.concatenate(length)


def squared_differences(values: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(E,) squared difference between the two nodes of each pair, summed over channels.

    Parameters
    ----------
    values : (N,) or (N, C) float
        Per node (a flattened raster).
    pairs : (E, 2) int
    """
    v = np.asarray(values, np.float64)
    d = v[pairs[:, 0]] - v[pairs[:, 1]]
    return d**2 if d.ndim == 1 else np.sum(d**2, axis=1)


def crf_energy(
    labels: np.ndarray, unary: np.ndarray, edges: np.ndarray, weights: np.ndarray, omega: float
) -> float:
    """Energy of a labelling.

    Parameters
    ----------
    labels : (N,) int
        Label index of each node.
    unary : (N, L) float
        D_i(l), the cost of giving node i label l.
    edges : (E, 2) int
        Node pairs.
    weights : (E,) float
        w_ij >= 0 of each pair.
    omega : float
        Weight of the pairwise term.
    """
    data = unary[np.arange(len(labels)), labels].sum()
    cut = labels[edges[:, 0]] != labels[edges[:, 1]] if len(edges) else np.zeros(0, bool)
    return float(data + omega * weights[cut].sum())


def binary_cut(
    unary: np.ndarray, edges: np.ndarray, weights: np.ndarray, omega: float
) -> np.ndarray:
    """The exact minimiser of a two-label Potts energy: one s-t min cut.

    Parameters as :func:`crf_energy` with L = 2. Returns (N,) labels in {0, 1}.
    """
    g = maxflow.Graph[float]()
    nodes = g.add_nodes(len(unary))
    # a node on the sink side takes label 1 and pays the source capacity
    g.add_grid_tedges(nodes, unary[:, 1], unary[:, 0])
    if len(edges):
        w = omega * weights
        g.add_edges(nodes[edges[:, 0]], nodes[edges[:, 1]], w, w)
    g.maxflow()
    return g.get_grid_segments(nodes).astype(np.int64)


def alpha_expansion(
    unary: np.ndarray,
    edges: np.ndarray,
    weights: np.ndarray,
    omega: float,
    init: np.ndarray | None = None,
    max_sweeps: int = 5,
    allowed: np.ndarray | None = None,
) -> np.ndarray:
    """Minimise a Potts energy by alpha-expansion moves (Boykov et al. 2001).

    Each move lets any node switch to one label alpha, solved exactly by a min cut; sweeps
    over all labels repeat until no move lowers the energy. The result is within a factor
    2 of the optimum for Potts energies; two labels get the exact :func:`binary_cut`.

    Parameters as :func:`crf_energy`; ``init`` defaults to the unary minimum over the
    allowed labels.

    allowed : (N, L) bool, optional
        The labels each node may take (every node at least one); by default all. A move
        to alpha is a cut on the nodes that allow alpha only, the others held at their
        label: with labels that are local (each allowed on a neighbourhood), a sweep costs
        O(N) rather than O(N L).

    Returns
    -------
    (N,) int labels.
    """
    n, n_labels = unary.shape
    if n == 0:
        return np.zeros(0, np.int64)
    if allowed is not None:
        allowed = np.asarray(allowed, bool)
        unary = np.where(allowed, unary, np.inf)
    if n_labels == 2 and allowed is None:
        return binary_cut(unary, edges, weights, omega)
    labels = unary.argmin(axis=1) if init is None else np.asarray(init, np.int64).copy()
    if n_labels == 1:
        return np.zeros(n, np.int64)
    w = omega * np.asarray(weights, np.float64)
    i, j = (edges[:, 0], edges[:, 1]) if len(edges) else (np.zeros(0, int),) * 2
    energy = crf_energy(labels, unary, edges, weights, omega)
    movable = np.ones((n, n_labels), bool) if allowed is None else allowed
    # a move repeated on the labels it last saw cannot lower the energy: refused then, it
    # is refused again; taken, it left the optimum of a move set that contains the new one
    changes, tried_at = 0, np.full(n_labels, -1)
    for _ in range(max_sweeps):
        improved = False
        for alpha in range(n_labels):
            if tried_at[alpha] == changes:
                continue
            tried_at[alpha] = changes
            proposal = _expand(labels, alpha, unary, i, j, w, movable[:, alpha])
            if proposal is None:
                continue
            e = crf_energy(proposal, unary, edges, weights, omega)
            if e < energy - 1e-9:
                labels, energy, improved = proposal, e, True
                changes += 1
                tried_at[alpha] = changes
        if not improved:
            break
    return labels


def _expand(labels, alpha, unary, i, j, w, movable) -> np.ndarray | None:
    """One alpha-expansion move among the ``movable`` nodes (the others, and those
    already alpha, keep their label); None when no node can move."""
    nodes = np.flatnonzero(movable & (labels != alpha))
    if len(nodes) == 0:
        return None
    local = np.full(len(labels), -1)
    local[nodes] = np.arange(len(nodes))
    keep_cost = unary[nodes, labels[nodes]].astype(np.float64)
    move_cost = unary[nodes, alpha].astype(np.float64)
    ci, cj = labels[i], labels[j]
    li, lj = local[i], local[j]
    # an edge to a node that keeps its label adds to the moving node's two costs
    for a, b, ca, cb in ((li, lj, ci, cj), (lj, li, cj, ci)):
        one = (a >= 0) & (b < 0)
        np.add.at(keep_cost, a[one], w[one] * (ca[one] != cb[one]))
        np.add.at(move_cost, a[one], w[one] * (cb[one] != alpha))
    # a Potts pair of movable nodes: both keep, i keeps and j moves, i moves, both move
    both = (li >= 0) & (lj >= 0)
    wb = w[both]
    pair = np.column_stack([wb * (ci[both] != cj[both]), wb, wb, np.zeros_like(wb)])
    x = pairwise_cut(
        np.column_stack([keep_cost, move_cost]), np.column_stack([li[both], lj[both]]), pair
    )
    out = labels.copy()
    out[nodes[x == 1]] = alpha
    return out


def pairwise_cut(unary: np.ndarray, edges: np.ndarray, pair: np.ndarray) -> np.ndarray:
    """Minimise a two-label energy with any pairwise terms by one s-t min cut.

    E(x) = sum_i D_i(x_i) + sum_(i,j) E_ij(x_i, x_j), x in {0, 1}, rewritten as
    E_ij = E00 + (E10 - E00) x_i + (E11 - E10) x_j + (E01 + E10 - E00 - E11)(1 - x_i) x_j
    (Kolmogorov and Zabih 2004). The minimum is exact when every pair is submodular,
    E01 + E10 >= E00 + E11; the few pairs that are not have their coupling clipped to 0.

    Parameters
    ----------
    unary : (N, 2) float
        D_i(0), D_i(1).
    edges : (E, 2) int
    pair : (E, 4) float
        E_ij(0, 0), E_ij(0, 1), E_ij(1, 0), E_ij(1, 1) of each edge.

    Returns
    -------
    (N,) int labels in {0, 1}.
    """
    n = len(unary)
    if n == 0:  # PyMaxflow refuses an empty graph
        return np.zeros(0, np.int64)
    cost1 = np.asarray(unary[:, 1], np.float64).copy()  # paid on the sink side, x = 1
    cost0 = np.asarray(unary[:, 0], np.float64).copy()
    if len(edges):
        i, j = edges[:, 0], edges[:, 1]
        e00, e01, e10, e11 = np.asarray(pair, np.float64).T
        lin_i, lin_j = e10 - e00, e11 - e10
        np.add.at(cost1, i, np.maximum(lin_i, 0))
        np.add.at(cost0, i, np.maximum(-lin_i, 0))
        np.add.at(cost1, j, np.maximum(lin_j, 0))
        np.add.at(cost0, j, np.maximum(-lin_j, 0))
    g = maxflow.Graph[float]()
    nodes = g.add_nodes(n)
    if len(edges):
        coupling = np.maximum(e01 + e10 - e00 - e11, 0.0)
        g.add_edges(nodes[i], nodes[j], coupling, np.zeros_like(coupling))
    g.add_grid_tedges(nodes, cost1, cost0)
    g.maxflow()
    return g.get_grid_segments(nodes).astype(np.int64)

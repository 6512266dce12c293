"""The prototype CRF (the super-pixel paper, section 5.2): each building super-pixel
takes a roof prototype; the prototypes are then refitted to what they won."""

from __future__ import annotations

import numpy as np

from modeling.shared.planes import point_plane_distances, ransac_plane
from workbench.graph_cuts import alpha_expansion

from .aggregation import SuperpixelGraph
from .options import SuperpixelOptions
from .plane_hypotheses import SuperpixelPoints


def label_prototypes(
    members: np.ndarray,
    prototypes: np.ndarray,
    pts: SuperpixelPoints,
    graph: SuperpixelGraph,
    options: SuperpixelOptions,
    anchors: np.ndarray | None = None,
) -> np.ndarray:
    """The prototype CRF (section 5.2): each building super-pixel takes a prototype.

    Unary: summed (truncated) point-to-plane distance of the super-pixel's points to the
    prototype; pairwise: b / (1 + g), weight ``omega_roof``. A prototype is offered to the
    super-pixels within ``prototype_reach`` rings of its anchor (:func:`prototype_reach`),
    so that a terrace of a thousand prototypes costs a thousand small cuts, not a thousand
    cuts of the whole terrace.

    Parameters
    ----------
    anchors : (P,) int, optional
        Super-pixel of each prototype's exemplar; None offers every prototype everywhere.

    Returns
    -------
    (len(members),) prototype index of each member.
    """
    index = np.full(graph.n, -1)
    index[members] = np.arange(len(members))
    e = graph.edges
    inside = (index[e[:, 0]] >= 0) & (index[e[:, 1]] >= 0)
    edges = np.stack([index[e[inside, 0]], index[e[inside, 1]]], axis=1)
    if anchors is None:
        allowed = np.ones((len(members), len(prototypes)), bool)
    else:
        allowed = prototype_reach(edges, len(members), index[anchors], options.prototype_reach)
    unary = np.full((len(members), len(prototypes)), np.inf)
    for row, i in enumerate(members):
        offered = np.flatnonzero(allowed[row])
        d = point_plane_distances(prototypes[offered], pts.of(i))  # (N_i, offered)
        unary[row, offered] = np.minimum(d, options.truncation_m).sum(axis=0)
    return alpha_expansion(
        unary, edges, graph.pairwise[inside], options.omega_roof, allowed=allowed
    )


def prototype_reach(edges: np.ndarray, n: int, anchors: np.ndarray, rings: int) -> np.ndarray:
    """(n, P) bool: the nodes within ``rings`` steps of each prototype's anchor on the
    adjacency ``edges`` (E, 2). A node farther than that from every anchor is offered the
    prototype of its nearest anchor (by steps); one that no anchor reaches, every one.

    An exemplar stands for hypotheses on adjacent super-pixels only (the similarity is
    sparse), so a prototype's cluster lies within one ring of its anchor; the further
    rings let it grow over super-pixels too small for a hypothesis of their own.
    """
    from scipy import sparse
    from scipy.sparse.csgraph import dijkstra

    ends = (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])
    step = sparse.csr_matrix((np.ones(2 * len(edges)), ends), shape=(n, n))
    P = len(anchors)
    reach = sparse.csr_matrix((np.ones(P), (anchors, np.arange(P))), shape=(n, P))
    grow = step + sparse.identity(n, format="csr")
    for _ in range(rings):
        reach = (grow @ reach).astype(bool).astype(np.float64)
    allowed = reach.toarray().astype(bool)
    lost = np.flatnonzero(~allowed.any(axis=1))
    if len(lost):
        _, _, source = dijkstra(
            step, indices=anchors, unweighted=True, min_only=True, return_predecessors=True
        )
        slot = np.full(n, -1)
        slot[anchors] = np.arange(P)
        nearest = slot[np.maximum(source[lost], 0)]
        found = source[lost] >= 0
        allowed[lost[found], nearest[found]] = True
        allowed[lost[~found]] = True
    return allowed


def refit_planes(
    members: np.ndarray, assignment: np.ndarray, prototypes: np.ndarray, pts, options
) -> np.ndarray:
    """Each used prototype refitted (RANSAC) to all points of the super-pixels it won."""
    out = prototypes.copy()
    for k in np.unique(assignment):
        p = np.concatenate([pts.of(i) for i in members[assignment == k]] or [np.empty((0, 3))])
        plane = ransac_plane(
            p, options.ransac_threshold_m, options.ransac_iterations, seed=options.seed
        )
        if plane is not None:
            out[k] = plane
    return out

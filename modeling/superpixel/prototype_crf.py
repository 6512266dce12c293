"""The prototype CRF (the super-pixel paper, section 5.2): each building super-pixel
takes a roof prototype; the prototypes are then refitted to what they won."""

from __future__ import annotations

import numpy as np

from workbench.graph_cuts import alpha_expansion
from workbench.planes import plane_heights, point_plane_distances, ransac_planes

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
    inner_edges: np.ndarray | None = None,
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
    inner_edges : (e,) int, optional
        Indices, in increasing order, of the ``graph.edges`` between two of ``members``
        (:func:`edges_within`); found here when not given, which reads every edge of the
        graph: a city's buildings give them at once instead.

    Returns
    -------
    (len(members),) prototype index of each member.
    """
    if inner_edges is None:
        owner = np.zeros(graph.n, np.int64)
        owner[members] = 1
        inner_edges = edges_within(graph.edges, owner)[1]
    # a node's row is where it sorts among the members
    sorter = np.argsort(members, kind="stable")
    edges = sorter[np.searchsorted(members, graph.edges[inner_edges], sorter=sorter)]
    if anchors is None:
        allowed = np.ones((len(members), len(prototypes)), bool)
    else:
        rows = sorter[np.searchsorted(members, anchors, sorter=sorter)]
        allowed = prototype_reach(edges, len(members), rows, options.prototype_reach)
    unary = np.full((len(members), len(prototypes)), np.inf)
    for row, i in enumerate(members):
        offered = np.flatnonzero(allowed[row])
        d = point_plane_distances(prototypes[offered], pts.of(i))  # (N_i, offered)
        unary[row, offered] = np.minimum(d, options.truncation_m).sum(axis=0)
    pairwise = graph.boundary[inner_edges] / (1.0 + graph.colour_distance[inner_edges])
    return alpha_expansion(unary, edges, pairwise, options.omega_roof, allowed=allowed)


def edges_within(edges: np.ndarray, owner: np.ndarray) -> list[np.ndarray]:
    """Per group 0..G of the nodes, the indices (increasing) of the ``edges`` (E, 2)
    whose two ends it owns (``owner`` (N,) int, 0 none): one sort of the edges instead
    of a pass over all of them per group."""
    a, b = owner[edges[:, 0]], owner[edges[:, 1]]
    group = np.where(a == b, a, 0)
    order = np.argsort(group, kind="stable")
    return np.split(order, np.cumsum(np.bincount(group, minlength=int(owner.max()) + 1))[:-1])


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
    used = np.unique(assignment)
    groups = [np.concatenate([pts.of(i) for i in members[assignment == k]]) for k in used]
    planes = ransac_planes(
        groups, options.ransac_threshold_m, options.ransac_iterations, seed=options.seed
    )
    fitted = np.isfinite(planes[:, 0])
    out[used[fitted]] = planes[fitted]
    return out


def cells_to_fitting_planes(
    labels: np.ndarray,
    assignment: np.ndarray,
    edges: np.ndarray,
    heights: np.ndarray,
    X: np.ndarray,
    Y: np.ndarray,
    planes: np.ndarray,
    inlier_m: float,
) -> np.ndarray:
    """(h, w) int prototype + 1 of each cell (0 off the building): its super-pixel's, but
    where that plane misses the cell's height by more than ``inlier_m`` and the plane of
    an adjacent super-pixel does not, that one's.

    A super-pixel across a ridge or a mansard's break takes one plane; its cells past the
    line keep it, and there the plane stands above the roof by its slope times their
    distance (``small`` seed 1: 55-94 cells of a face 1-11 m over the DSM, and the roof's
    vertex there 2-7 m over the building's top). The roof is the plane that fits.

    Parameters
    ----------
    labels : (h, w) int
        Super-pixel of each cell (rows of ``assignment``), -1 off the building.
    assignment : (m,) int
        Prototype of each super-pixel.
    edges : (E, 2) int
        Adjacent super-pixels.
    heights : (h, w) float
        The DSM, metres, NaN unknown.
    X, Y : (h, w) float
        Cell centres, metres.
    planes : (P, 4)
    inlier_m : float
        The planes' inlier distance (their RANSAC's).
    """
    on = labels >= 0
    faces = np.where(on, assignment[np.where(on, labels, 0)] + 1, 0)
    best_err = np.full(labels.shape, np.inf)
    best = np.full(labels.shape, -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        own = np.moveaxis(planes[faces - 1], -1, 0)  # (4, h, w): each cell's plane
        err_own = np.abs(plane_heights(own, X, Y) - heights)
    misfit = on & (err_own > inlier_m)  # NaN heights compare False: kept
    if not misfit.any():
        return faces
    # the prototypes of each super-pixel's neighbours
    pairs = np.concatenate([edges, edges[:, ::-1]])
    offered = np.unique(np.c_[pairs[:, 0], assignment[pairs[:, 1]]], axis=0)
    rows, cols = np.nonzero(misfit)
    sp = labels[rows, cols]
    for k in np.unique(offered[:, 1]):
        has = np.zeros(len(assignment), bool)
        has[offered[offered[:, 1] == k, 0]] = True
        take = has[sp]
        r, c = rows[take], cols[take]
        with np.errstate(invalid="ignore", divide="ignore"):
            err = np.abs(plane_heights(planes[k], X[r, c], Y[r, c]) - heights[r, c])
        better = err < best_err[r, c]
        best_err[r[better], c[better]] = err[better]
        best[r[better], c[better]] = k
    moved = misfit & (best >= 0) & (best_err <= inlier_m)
    faces[moved] = best[moved] + 1
    return faces

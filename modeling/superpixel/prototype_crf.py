"""The prototype CRF (the super-pixel paper, section 5.2): each building super-pixel
takes a roof prototype; the prototypes are then refitted to what they won."""

from __future__ import annotations

import numpy as np

from modeling.shared.graph_cuts import alpha_expansion
from modeling.shared.planes import point_plane_distances, ransac_plane

from .aggregation import SuperpixelGraph
from .options import SuperpixelOptions
from .plane_hypotheses import SuperpixelPoints


def label_prototypes(
    members: np.ndarray,
    prototypes: np.ndarray,
    pts: SuperpixelPoints,
    graph: SuperpixelGraph,
    options: SuperpixelOptions,
) -> np.ndarray:
    """The prototype CRF (section 5.2): each building super-pixel takes a prototype.

    Unary: summed (truncated) point-to-plane distance of the super-pixel's points to the
    prototype; pairwise: b / (1 + g), weight ``omega_roof``.

    Returns
    -------
    (len(members),) prototype index of each member.
    """
    unary = np.zeros((len(members), len(prototypes)))
    for row, i in enumerate(members):
        d = point_plane_distances(prototypes, pts.of(i))  # (N_i, P)
        unary[row] = np.minimum(d, options.truncation_m).sum(axis=0)
    index = np.full(graph.n, -1)
    index[members] = np.arange(len(members))
    e = graph.edges
    inside = (index[e[:, 0]] >= 0) & (index[e[:, 1]] >= 0)
    edges = np.stack([index[e[inside, 0]], index[e[inside, 1]]], axis=1)
    return alpha_expansion(unary, edges, graph.pairwise[inside], options.omega_roof)


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

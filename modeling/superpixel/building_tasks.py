"""Sections 5.1-5.3 of the super-pixel paper as one task per building.

A building's roof is found from its own super-pixels alone: their DSM points, the edges
between them and its window of the rasters. :func:`building_shares` cuts these out of the
whole grid, each with its super-pixels numbered from 0, so that a task carries a few
hundred kilobytes to whichever worker runs it (:mod:`workbench.engine`) and its result
does not depend on the others, nor on the number of workers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from modeling.shared.opened_parts import CEILING_MARGIN_CELLS
from workbench.model_run import Building
from workbench.raster import Grid

from .aggregation import SuperpixelGraph
from .options import SuperpixelOptions
from .plane_hypotheses import SuperpixelPoints, plane_hypotheses
from .prototype_crf import (
    cells_to_fitting_planes,
    edges_within,
    label_prototypes,
    refit_planes,
)
from .prototypes import roof_prototypes
from .rooftop import model_building, observed_faces, with_unseen_parts

ROOF_STEPS = ("plane_hypotheses", "prototypes", "prototype_crf", "roof_modeling")


@dataclass
class BuildingShare:
    """One building's super-pixels and its window of the rasters.

    Attributes
    ----------
    id : int
        Building number, 1..
    window : (r0, r1, c0, c1)
        Rows and columns of the whole grid, one cell of margin.
    grid : Grid
        The window's grid.
    graph : SuperpixelGraph
        The building's super-pixels 0..m-1 (in the whole grid's order) and the edges
        between two of them; ``labels`` is the window, -1 off the building.
    points : SuperpixelPoints
        Their DSM points, world metres.
    dsm, dtm : (h, w) float
        The window's DSM and DTM, metres, NaN unknown.
    ceiling : (h, w) float or None
        The fusion's ceiling over the window's cells no view saw, metres
        (:mod:`fusion.hidden_ceiling`); None without one.
    """

    id: int
    window: tuple[int, int, int, int]
    grid: Grid
    graph: SuperpixelGraph
    points: SuperpixelPoints
    dsm: np.ndarray
    dtm: np.ndarray
    ceiling: np.ndarray | None = None

    @property
    def known(self) -> np.ndarray:
        """(h, w) bool the cells of the window with a height."""
        return np.isfinite(self.dsm)


@dataclass
class BuildingRoofs:
    """What a building's task gives back.

    Attributes
    ----------
    id : int
    parts : list of Building
        Its closed meshes (one per part), ids set.
    faces : (h, w) int32
        Prototype face + 1 of every cell of the window the roof covers, 0 elsewhere.
    seconds : {step: seconds}
        Time in each of ``ROOF_STEPS``.
    """

    id: int
    parts: list[Building]
    faces: np.ndarray
    seconds: dict = field(default_factory=dict)


def building_shares(
    graph: SuperpixelGraph,
    owner: np.ndarray,
    pts: SuperpixelPoints,
    dsm: np.ndarray,
    dtm: np.ndarray,
    grid: Grid,
    ceiling: np.ndarray | None = None,
) -> list[BuildingShare]:
    """Each building's share of the whole grid (:class:`BuildingShare`).

    Parameters
    ----------
    graph : SuperpixelGraph
        Every super-pixel.
    owner : (N,) int
        Building of each super-pixel, 0 none.
    pts : SuperpixelPoints
        Every super-pixel's DSM points.
    dsm, dtm : (H, W) float
        Metres.
    grid : Grid
    ceiling : (H, W) float or None
        The fusion's ceiling over the cells no view saw, metres.
    """
    labels = graph.labels
    n = int(owner.max())
    cell_building = owner[labels]
    boxes = building_boxes(cell_building, n)
    members_of = np.split(np.argsort(owner, kind="stable"), np.cumsum(np.bincount(owner)))
    inner_edges = edges_within(graph.edges, owner)
    shares = []
    for b in range(1, n + 1):
        members, inner = members_of[b], inner_edges[b]  # both increasing
        r0, r1, c0, c1 = boxes[b]
        on = cell_building[r0:r1, c0:c1] == b
        local = np.full(on.shape, -1, np.int64)
        local[on] = np.searchsorted(members, labels[r0:r1, c0:c1][on])
        sub = SuperpixelGraph(
            local, graph.count[members], graph.class_sum[members], graph.colour[members],
            graph.height_median[members],
            None if graph.plane_residual is None else graph.plane_residual[members],
            np.searchsorted(members, graph.edges[inner]), graph.boundary[inner],
            graph.colour_distance[inner],
        )  # fmt: skip
        shares.append(BuildingShare(
            b, (int(r0), int(r1), int(c0), int(c1)), grid.window(slice(r0, r1), slice(c0, c1)),
            sub, points_of(pts, members), dsm[r0:r1, c0:c1].copy(), dtm[r0:r1, c0:c1].copy(),
            None if ceiling is None else ceiling[r0:r1, c0:c1].copy(),
        ))  # fmt: skip
    return shares


def points_of(pts: SuperpixelPoints, members: np.ndarray) -> SuperpixelPoints:
    """The points of super-pixels ``members`` alone, numbered 0..len(members)-1."""
    lengths = pts.ends[members] - pts.starts[members]
    ends = np.cumsum(lengths)
    starts = ends - lengths
    take = np.repeat(pts.starts[members] - starts, lengths) + np.arange(int(lengths.sum()))
    return SuperpixelPoints(pts.points[take], starts, ends)


def no_roofs(share: BuildingShare, reason: str) -> BuildingRoofs:
    """The answer of a building whose task failed (``reason``): no part, no face."""
    return BuildingRoofs(share.id, [], np.zeros(share.known.shape, np.int32),
                         dict.fromkeys(ROOF_STEPS, 0.0))  # fmt: skip


def model_building_roofs(
    share: BuildingShare, options: SuperpixelOptions, edge_reach_m: float
) -> BuildingRoofs:
    """Sections 5.1-5.3 on one building: plane hypotheses, prototypes, the prototype CRF
    and the refitted planes, then the roof polygons lifted and walled (a task)."""
    graph, pts = share.graph, share.points
    members = np.arange(graph.n)
    neighbours = adjacency_lists(graph.edges)
    seconds = dict.fromkeys(ROOF_STEPS, 0.0)

    def timed(step: str, fn, *args):
        t0 = time.perf_counter()
        result = fn(*args)
        seconds[step] += time.perf_counter() - t0
        return result

    hyps = timed("plane_hypotheses", plane_hypotheses, members, pts, neighbours, options)
    protos, anchors = timed("prototypes", _prototypes, hyps, members, graph, neighbours, options)
    if not len(protos):
        return BuildingRoofs(share.id, [], np.zeros(share.known.shape, np.int32), seconds)
    inner = np.arange(len(graph.edges))
    assign = timed("prototype_crf", label_prototypes, members, protos, pts, graph, options,
                   anchors, inner)  # fmt: skip
    protos = timed("prototype_crf", refit_planes, members, assign, protos, pts, options)
    heights = np.full(share.known.shape, np.nan)
    r, c = share.grid.cell_index(pts.points[:, 0], pts.points[:, 1], clip=True)
    heights[r, c] = pts.points[:, 2]
    X, Y = share.grid.cell_centers()
    crop = timed("prototype_crf", cells_to_fitting_planes, graph.labels, assign, graph.edges,
                 heights, X, Y, protos, options.ransac_threshold_m)  # fmt: skip
    crop = observed_faces(crop, share.known, int(round(edge_reach_m / share.grid.gsd)))
    if not options.all_building:  # a cloud of one building: its unknown cells are off it
        crop = with_unseen_parts(crop, protos, share.dsm, share.dtm, X, Y, share.ceiling,
                                 int(round(edge_reach_m / share.grid.gsd)),
                                 CEILING_MARGIN_CELLS * share.grid.gsd)  # fmt: skip
    parts = timed("roof_modeling", model_building, crop, share.grid, protos, share.dtm, options)
    counts = {"superpixels": graph.n, "hypotheses": len(hyps), "prototypes": len(protos)}
    for k, part in enumerate(parts):
        part.id = f"{share.id}" if k == 0 else f"{share.id}-{k}"
        part.record.update(counts)
    return BuildingRoofs(share.id, parts, crop.astype(np.int32), seconds)


def adjacency_lists(edges: np.ndarray) -> dict[int, list[int]]:
    """{node: its neighbours} on the ``edges`` (E, 2), each node's neighbours in the order
    of the edges that name it; only nodes with an edge appear."""
    if not len(edges):
        return {}
    node = np.r_[edges[:, 0], edges[:, 1]]
    other = np.r_[edges[:, 1], edges[:, 0]]
    order = np.lexsort((np.tile(np.arange(len(edges)), 2), node))
    node, other = node[order], other[order]
    starts = np.flatnonzero(np.r_[True, node[1:] != node[:-1]])
    lists = np.split(other, starts[1:])
    return dict(zip(node[starts].tolist(), (part.tolist() for part in lists), strict=True))


def _prototypes(hyps, members, graph: SuperpixelGraph, neighbours, options):
    """Section 5.2's prototypes and their anchors, or with no plane anywhere one flat roof
    at the median, anchored nowhere (allowed everywhere)."""
    if hyps:
        return roof_prototypes(hyps, neighbours, options)
    z = np.nanmedian(graph.height_median[members])
    flat = np.array([[0.0, 0.0, 1.0, -z]]) if np.isfinite(z) else np.empty((0, 4))
    return flat, None


def building_boxes(cell_building: np.ndarray, n: int) -> np.ndarray:
    """(n + 1, 4) row and column bounds (r0, r1, c0, c1), one cell of margin, of each
    building 1..n in a raster of building ids (row 0 unused)."""
    H, W = cell_building.shape
    rr, cc = np.nonzero(cell_building)
    bb = cell_building[rr, cc]
    lo_r, lo_c = np.full(n + 1, H), np.full(n + 1, W)
    hi_r, hi_c = np.full(n + 1, -1), np.full(n + 1, -1)
    np.minimum.at(lo_r, bb, rr)
    np.minimum.at(lo_c, bb, cc)
    np.maximum.at(hi_r, bb, rr)
    np.maximum.at(hi_c, bb, cc)
    return np.stack(
        [np.maximum(lo_r - 1, 0), np.minimum(hi_r + 2, H), np.maximum(lo_c - 1, 0),
         np.minimum(hi_c + 2, W)], axis=1
    )  # fmt: skip

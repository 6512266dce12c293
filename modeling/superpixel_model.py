"""The super-pixel modeling path (the super-pixel paper, sections 4.1 to 5.3), on arrays.

Each step of the paper is one function here or in the module named after it:
quickshift_superpixels (4.1), superpixel_graph (aggregation), refine_classes (4.2, eq. 2-3),
split_buildings, plane_hypotheses (5.1), roof_prototypes (5.2), label_prototypes (5.2,
the prototype CRF), model_building (5.3).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import shapely
from shapely.geometry import mapping

from workbench.meshes import is_watertight, unpaired_edges
from workbench.raster import Grid

from .aggregate import SuperpixelGraph
from .crf import alpha_expansion
from .planes import plane_heights, point_plane_distances, ransac_plane
from .prototypes import cluster_prototypes, hypothesis_similarity
from .roof_mesh import extrude_faces, face_polygons, merge_smallest_face, untangle_diagonals
from .roof_types import roof_type
from .superpixels import HEIGHT_LAB


@dataclass
class SuperpixelOptions:
    """Parameters of the path (the paper's values where it gives them).

    Attributes
    ----------
    sigma, tau, ratio : Quickshift kernel width and largest link, pixels; colour weight.
    segment_on : "ortho" (the paper) or "relief" (the DSM's normals,
        :func:`~modeling.superpixels.relief_image`); None: the relief for point-cloud
        fusions, whose ortho is one grey level or intensity per cell, the ortho otherwise.
    height_weight : Lab units per metre of the DSM's height, segmented beside the ortho's
        colour (:func:`~modeling.superpixels.colour_height_image`); 0: the colour alone,
        as in the paper.
    omega_class : weight of the class CRF's pairwise term (eq. 2; the paper: 3); None
        chooses it on the scene's training strokes (:func:`choose_omega_class`).
    omega_roof : weight of the prototype CRF's pairwise term (the paper: 5).
    opening_m : radius of the opening that splits weakly touching buildings, metres.
    min_area_m2 : smallest building kept, square metres.
    ransac_threshold_m, ransac_iterations : RANSAC inlier distance and iterations.
    min_plane_points : a super-pixel with fewer heights borrows its neighbours' for its
        hypothesis.
    prototype_tolerance_m : affinity propagation's preference is minus this: a hypothesis
        joins another's prototype when that explains its points to about this distance.
    truncation_m : point-to-plane distances are truncated here in the prototype unary, so
        that a tree over a roof does not decide its plane.
    edge_reach_m : unseen cells of a building's super-pixels this close to a seen cell of
        it stay in the building (:func:`observed_faces`), metres. None: 1 m for fused
        views, whose occlusions leave building edges unseen; 0 for point clouds, which see
        the eaves from above.
    simplify_m : tolerance of the roof polygons' simplification, metres (None:
        ``SIMPLIFY_CELLS`` cells, which removes the cell staircase and little more).
    regularise_deg : outline sides this close to the building's dominant directions are
        put on them (:mod:`~modeling.outline_regularity`); 0: as simplified.
    all_building : every super-pixel with a height is building, whatever the classes say,
        and no opening splits it: for clouds of one building (City3D's building
        instances), which hold no ground to classify against.
    seed : RANSAC and affinity propagation seed.
    workers : Quickshift tiles segmented at once, in threads; None: every core this process
        has. The labels do not depend on it.
    """

    sigma: float = 2.0
    tau: float = 8.0
    ratio: float = 1.0
    segment_on: str | None = None
    height_weight: float = HEIGHT_LAB
    omega_class: float | None = 3.0
    omega_roof: float = 5.0
    opening_m: float = 1.0
    min_area_m2: float = 20.0
    ransac_threshold_m: float = 0.15
    ransac_iterations: int = 200
    min_plane_points: int = 6
    prototype_tolerance_m: float = 0.25
    truncation_m: float = 2.0
    simplify_m: float | None = None
    regularise_deg: float = 0.0
    edge_reach_m: float | None = None
    all_building: bool = False
    seed: int = 0
    workers: int | None = None


def refine_classes(graph: SuperpixelGraph, omega: float) -> np.ndarray:
    """The class CRF on super-pixels (eq. 2 and 3), by alpha-expansion over the classes.

    Unary: -log of the super-pixel's aggregated (mean) class likelihood, counted once per
    cell of the super-pixel, so that it grows with the area as the pairwise term (the
    number of boundary cells) grows with the perimeter; pairwise: b / (1 + g) for
    differing labels.

    Returns
    -------
    (N,) class codes 1..C.
    """
    likelihood = graph.class_sum / np.maximum(graph.count, 1)[:, None]
    unary = -np.log(np.clip(likelihood, 1e-6, 1.0)) * graph.count[:, None]
    return alpha_expansion(unary, graph.edges, graph.pairwise, omega) + 1


# 2.25 cells: on the AHN3 clouds 2, 2.25, 2.5 and 3 cells give median RMS 0.226, 0.234,
# 0.250 and 0.282 m with 122, 107, 103 and 95 triangles; on the synthetic city 2 and 2.25
# give the same heights (RMSE 1.63 and 1.64 m) with 10 % fewer triangles
SIMPLIFY_CELLS = 2.25
OMEGA_CANDIDATES = (0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 8.0, 12.0)


def choose_omega_class(graph: SuperpixelGraph, labels: np.ndarray, strokes: np.ndarray) -> dict:
    """Pick the class CRF's omega by its mean class accuracy on the training strokes.

    Parameters
    ----------
    graph : SuperpixelGraph
    labels : (H, W) int
        Super-pixels.
    strokes : (H, W) int
        Training labels 1..4, 0 unlabelled.

    Returns
    -------
    {"omega": best, "scores": {omega: mean class accuracy}}. The strokes also trained the
    per-view forest, so the scores favour trusting it (small omega) a little.
    """
    from workbench.metrics import classification

    scores = {}
    for omega in OMEGA_CANDIDATES:
        pred = refine_classes(graph, omega)[labels]
        c = classification(np.where(strokes > 0, pred, 0), strokes)
        scores[omega] = c.get("mean_class_accuracy", 0.0)
    best = max(scores, key=lambda w: (scores[w], -abs(np.log(w / 3.0))))  # ties: nearest 3
    return {"omega": best, "scores": scores}


@dataclass
class SuperpixelPoints:
    """The DSM points of every super-pixel: ``points[starts[i]:ends[i]]`` (world metres)."""

    points: np.ndarray
    starts: np.ndarray
    ends: np.ndarray

    def of(self, i: int) -> np.ndarray:
        return self.points[self.starts[i] : self.ends[i]]


def superpixel_points(labels: np.ndarray, dsm: np.ndarray, grid: Grid) -> SuperpixelPoints:
    """Group the DSM's known cells, as 3D points, by super-pixel."""
    X, Y = grid.cell_centers()
    ok = np.isfinite(dsm)
    lab = labels[ok]
    order = np.argsort(lab, kind="stable")
    pts = np.column_stack([X[ok], Y[ok], dsm[ok]])[order]
    n = int(labels.max()) + 1
    sl = lab[order]
    return SuperpixelPoints(
        pts, np.searchsorted(sl, np.arange(n)), np.searchsorted(sl, np.arange(n), side="right")
    )


def plane_hypotheses(
    members: np.ndarray,
    pts: SuperpixelPoints,
    adjacency: dict[int, list[int]],
    options: SuperpixelOptions,
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """A RANSAC plane for each super-pixel of a building (section 5.1).

    Super-pixels with at least ``min_plane_points`` heights get a plane of their own. One
    with fewer, none of whose neighbours has a plane, borrows its neighbours' heights,
    ring by ring (two rings at most): on coarse rasters, such as LiDAR at its point
    spacing, whole roof sides are made of such super-pixels and would otherwise get no
    hypothesis at all.

    Parameters
    ----------
    adjacency : {super-pixel: adjacent super-pixels}

    Returns
    -------
    {super-pixel: (plane (4,), the points it was fitted to (N, 3))} for the super-pixels
    with enough points and a roof-like plane.
    """
    inside = set(int(i) for i in members)
    out = {}

    def fit(i: int, group: set[int]) -> None:
        points = np.concatenate([pts.of(j) for j in sorted(group)])
        plane = ransac_plane(
            points, options.ransac_threshold_m, options.ransac_iterations, seed=options.seed
        )
        if plane is not None:
            out[i] = (plane, points)

    small = []
    for i in map(int, members):
        if len(pts.of(i)) >= options.min_plane_points:
            fit(i, {i})
        else:
            small.append(i)
    own = set(out)
    for i in small:
        if any(k in own for k in adjacency.get(i, ())):
            continue  # a neighbour's plane can stand for it
        group, ring = {i}, {i}
        for _ in range(2):
            ring = {k for j in ring for k in adjacency.get(j, ()) if k in inside} - group
            group |= ring
            if sum(len(pts.of(j)) for j in group) >= options.min_plane_points:
                break
        fit(i, group)
    return out


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


def observed_faces(faces: np.ndarray, observed: np.ndarray, reach: int) -> np.ndarray:
    """Face labels restricted to observed cells and to unobserved cells within ``reach``
    cells of an observed cell of the building, keeping unobserved cells enclosed by it.

    Cells no view saw beside a wall are partly the roof's edge (the fusion leaves a
    building's outermost cells unseen) and partly occluded ground: a super-pixel that
    straddles them would otherwise carry its roof out over the street, while dropping
    them all cuts the roof short. On the small city, a reach of 1 m keeps the footprint
    quality (0.887 against 0.893 with none) and lowers the height RMSE from 4.95 to
    1.66 m: nearly all of it came from missed edge cells of tall buildings.

    Parameters
    ----------
    faces : (h, w) int
        Face label + 1 per cell, 0 outside the building.
    observed : (h, w) bool
        Cells with a known height.
    reach : int
        Cells.
    """
    seen = (observed & (faces > 0)).astype(np.uint8)
    if reach > 0:
        near = cv2.dilate(seen, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)) > 0
    else:
        near = seen > 0
    kept = np.where(observed | near, faces, 0)
    gaps = (kept == 0).astype(np.uint8)
    n, comp = cv2.connectedComponents(gaps, connectivity=4)
    border = np.unique(np.concatenate([comp[0], comp[-1], comp[:, 0], comp[:, -1]]))
    enclosed = (gaps > 0) & ~np.isin(comp, border)
    return np.where(enclosed, faces, kept)


@dataclass
class BuildingModel:
    """One modelled building: mesh (world metres) and its model.json record."""

    vertices: np.ndarray
    triangles: np.ndarray
    record: dict = field(default_factory=dict)


def model_building(
    face_raster: np.ndarray,
    grid: Grid,
    planes: np.ndarray,
    ground: np.ndarray,
    options: SuperpixelOptions,
) -> list[BuildingModel]:
    """Rooftop modeling (section 5.3): the faces become straight-edged polygons (a
    topology-preserving simplification of their shared boundaries), each vertex is lifted
    to its face's plane, walls go down to the ground, and the mesh is closed.

    Each 4-connected part of the building becomes one model (parts below
    ``min_area_m2`` are dropped). A part whose simplified mesh is not closed is rebuilt
    from its unsimplified cell outlines; if that is not closed either, its smallest face
    gives way to a neighbour until it is (counted in ``faces_merged_for_closure``).

    Parameters
    ----------
    face_raster : (h, w) int
        Prototype index + 1 of every cell of the building, 0 elsewhere (a crop).
    grid : Grid
        The crop's grid.
    planes : (P, 4)
        Prototype planes.
    ground : (h, w) float
        DTM of the crop, metres.

    Returns
    -------
    list of BuildingModel, largest first.
    """
    faces = untangle_diagonals(face_raster)
    n, parts, stats, _ = cv2.connectedComponentsWithStats(
        (faces > 0).astype(np.uint8), connectivity=4
    )
    out = []
    for k in np.argsort(-stats[:, cv2.CC_STAT_AREA]):
        if k == 0 or stats[k, cv2.CC_STAT_AREA] * grid.gsd**2 < options.min_area_m2:
            continue
        part = np.where(parts == k, faces, 0)
        g = ground[part > 0]
        g = g[np.isfinite(g)] if np.isfinite(g).any() else ground[np.isfinite(ground)]
        base = float(g.min()) if len(g) else np.inf  # unknown: just under the roof
        simplify = (
            options.simplify_m if options.simplify_m is not None else SIMPLIFY_CELLS * grid.gsd
        )
        merged = 0
        while True:
            model = _closed_model(part, grid, planes, base, simplify, options.regularise_deg)
            closed = model is not None and model.record["watertight"]
            if closed or len(np.unique(part[part > 0])) == 1:
                break
            # faces meeting at a vertex can leave two parts of the roof touching along a
            # vertical line there (not a manifold): give up the smallest face there, retry
            part = merge_smallest_face(part, _faces_at_open_edges(model, part, grid))
            merged += 1
        if model is not None:
            model.record["faces_merged_for_closure"] = merged
            out.append(model)
    return out


def _faces_at_open_edges(
    model: BuildingModel | None, faces: np.ndarray, grid: Grid
) -> np.ndarray | None:
    """Face labels of the cells within one cell of the ends of the model's unpaired
    edges (None without a model, or when every edge is paired)."""
    if model is None:
        return None
    ends = np.unique(unpaired_edges(model.triangles))
    if not len(ends):
        return None
    row, col = grid.cell_index(*model.vertices[ends, :2].T, clip=True)
    near = np.zeros(faces.shape, bool)
    near[row, col] = True
    near = cv2.dilate(near.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    return np.unique(faces[near & (faces > 0)])


def _closed_model(
    faces: np.ndarray,
    grid: Grid,
    planes: np.ndarray,
    ground: float,
    simplify: float,
    regularise_deg: float = 0.0,
) -> BuildingModel | None:
    """The part simplified by ``simplify`` (and regularised), else unsimplified when that
    is not closed (or the triangulation fails); None when neither gives a model."""
    fallback = None
    for tolerance, regular in ((simplify, regularise_deg), (1e-3, 0.0)):
        try:
            model = _model_part(faces, grid, planes, ground, tolerance, regular)
        except shapely.errors.GEOSException:  # a degenerate polygon after simplification
            continue
        if model is not None and model.record["watertight"]:
            return model
        fallback = fallback or model
    return fallback


def _model_part(
    faces: np.ndarray,
    grid: Grid,
    planes: np.ndarray,
    ground: float,
    tolerance: float,
    regularise_deg: float = 0.0,
) -> BuildingModel | None:
    polygons, labels = face_polygons(faces, grid, tolerance, regularise_deg=regularise_deg)
    if not polygons:
        return None
    face_planes = [planes[k - 1] for k in labels]
    outline = shapely.union_all(polygons)
    edge = outline.boundary
    roof_z, eave_z = [], []
    for poly, plane in zip(polygons, face_planes, strict=True):
        xy = np.asarray(poly.exterior.coords)
        z = plane_heights(plane, xy[:, 0], xy[:, 1])
        roof_z.append(z)
        on_outline = shapely.distance(shapely.points(xy), edge) < 1e-6
        eave_z.append(z[on_outline])
    roof_z = np.concatenate(roof_z)
    eave_z = np.concatenate(eave_z)
    base = min(ground, float(roof_z.min()) - 0.5)  # a floor under every roof vertex
    vertices, triangles = extrude_faces(polygons, face_planes, base)
    used = sorted(set(labels))
    areas, heights = [], []
    for u in used:
        mine = [p for p, k in zip(polygons, labels, strict=True) if k == u]
        area = sum(p.area for p in mine)
        areas.append(area)
        heights.append(
            sum(p.area * plane_heights(planes[u - 1], *p.centroid.coords[0]) for p in mine) / area
        )
    areas, heights = np.array(areas), np.array(heights)
    record = {
        "footprint": mapping(outline),
        "roof_planes": [
            {
                "normal": planes[u - 1][:3].round(5).tolist(),
                "offset": round(float(planes[u - 1][3]), 4),
                "area_m2": round(float(a), 2),
            }
            for u, a in zip(used, areas, strict=True)
        ],
        "roof_type": roof_type(
            planes[np.array(used) - 1],
            areas,
            heights,
            eave_z,
            ridge_z=float(roof_z.max()),
            centre=(outline.centroid.x, outline.centroid.y, np.sqrt(outline.area)),
        ),
        "base_z": round(base, 3),
        "eave_z": round(float(eave_z.min() if len(eave_z) else roof_z.min()), 3),
        "ridge_z": round(float(roof_z.max()), 3),
        "faces": int(len(triangles)),
        "watertight": is_watertight(vertices, triangles),
    }
    return BuildingModel(vertices, triangles, record)

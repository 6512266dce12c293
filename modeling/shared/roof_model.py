"""A closed roof model from labelled faces and their planes: the faces straightened
into polygons, lifted to their planes, walled down to a floor, named by roof type. Shared
by the paths that model roofs as planar faces on a grid (super-pixel prototypes, the voxel
path's pitched roofs)."""

from __future__ import annotations

import cv2
import numpy as np
import shapely

from workbench.meshes import is_watertight, unpaired_edges
from workbench.model_run import Building, Surface
from workbench.planes import plane_heights
from workbench.raster import Grid

from .roof_mesh import extrude_faces, face_polygons, merge_smallest_face
from .roof_types import roof_type

LOCAL_MENDS = 4  # closing attempts that move only the cells at the open edges


def closed_roof_model(
    faces: np.ndarray,
    grid: Grid,
    planes: np.ndarray,
    ground: float,
    simplify: float,
    regularise_deg: float = 0.0,
) -> Building | None:
    """One closed model of a 4-connected part's faces.

    The faces are simplified by ``simplify`` (and regularised); a mesh that is not closed
    is rebuilt from the unsimplified cell outlines; if that is not closed either, the
    cells at its open edges of the smallest face there (after ``LOCAL_MENDS`` attempts,
    that whole face) go to the neighbour whose plane lies nearest its own, until it is
    (counted in the record's ``faces_merged_for_closure``): faces meeting at a vertex can
    leave two parts of the roof touching along a vertical line there, which is not a
    manifold. A face with no neighbouring face to go to ends the mending, and the model
    is returned as it is (not watertight).

    Parameters
    ----------
    faces : (h, w) int
        Plane index + 1 of every cell of the part, 0 elsewhere.
    grid : Grid
        The faces' grid (world or a building's local frame, metres).
    planes : (P, 4)
        Roof planes in the grid's coordinates.
    ground : float
        Floor height, metres (lowered to half a metre under the lowest roof vertex).
    simplify : float
        Simplification tolerance, metres.

    Returns
    -------
    Building (id left empty) or None when no face gives a polygon.
    """
    merged, local = 0, True
    model = _closed_model(faces, grid, planes, ground, simplify, regularise_deg)
    while not (model is not None and _watertight(model)) and len(np.unique(faces[faces > 0])) > 1:
        near = _cells_at_open_edges(model, faces, grid)
        among = np.unique(faces[near & (faces > 0)]) if near is not None else None
        # first only the cells at the open edges, then whole faces
        within = near if local and merged < LOCAL_MENDS else None
        mended = merge_smallest_face(faces, among, planes, grid, within)
        if np.array_equal(mended, faces):  # the face has no neighbouring face to go to
            if within is None:
                break
            local = False  # the same faces, the same model: whole faces next
            continue
        faces, merged = mended, merged + 1
        model = _closed_model(faces, grid, planes, ground, simplify, regularise_deg)
    if model is not None:
        model.record["faces_merged_for_closure"] = merged
    return model


def _cells_at_open_edges(
    model: Building | None, faces: np.ndarray, grid: Grid
) -> np.ndarray | None:
    """(H, W) bool: the cells within one cell of the ends of the model's unpaired edges
    (None without a model, or when every edge is paired)."""
    if model is None:
        return None
    ends = np.unique(unpaired_edges(model.mesh.triangles))
    if not len(ends):
        return None
    row, col = grid.cell_index(*model.mesh.vertices[ends, :2].T, clip=True)
    near = np.zeros(faces.shape, bool)
    near[row, col] = True
    return cv2.dilate(near.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0


def _closed_model(
    faces: np.ndarray,
    grid: Grid,
    planes: np.ndarray,
    ground: float,
    simplify: float,
    regularise_deg: float = 0.0,
) -> Building | None:
    """The part simplified by ``simplify`` (and regularised), else unsimplified when that
    is not closed (or the triangulation fails); None when neither gives a model."""
    fallback = None
    for tolerance, regular in ((simplify, regularise_deg), (1e-3, 0.0)):
        try:
            model = _model_part(faces, grid, planes, ground, tolerance, regular)
        except shapely.errors.GEOSException:  # a degenerate polygon after simplification
            continue
        if model is not None and _watertight(model):
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
) -> Building | None:
    polygons, labels = face_polygons(faces, grid, tolerance, regularise_deg=regularise_deg)
    if not polygons:
        return None
    face_planes = [planes[k - 1] for k in labels]
    outline = shapely.union_all(polygons)
    edge = outline.boundary
    roof_z, eave_xyz = [], []
    for poly, plane in zip(polygons, face_planes, strict=True):
        xy = np.asarray(poly.exterior.coords)[:-1]  # the ring's closing vertex once
        z = plane_heights(plane, xy[:, 0], xy[:, 1])
        roof_z.append(z)
        on_outline = shapely.distance(shapely.points(xy), edge) < 1e-6
        eave_xyz.append(np.column_stack([xy[on_outline], z[on_outline]]))
    roof_z = np.concatenate(roof_z)
    # each outline vertex once, at the highest roof it carries: faces meeting at an
    # outline vertex would count it once per face
    eave_xyz = np.concatenate(eave_xyz)
    eave_xyz = eave_xyz[np.lexsort((-eave_xyz[:, 2], eave_xyz[:, 1], eave_xyz[:, 0]))]
    _, first = np.unique(np.round(eave_xyz[:, :2], 6), axis=0, return_index=True)
    eave_z = eave_xyz[first, 2]
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
    planes_used = planes[np.array(used) - 1]
    kind = roof_type(
        planes_used, areas, heights, eave_z, ridge_z=float(roof_z.max()),
        centre=(outline.centroid.x, outline.centroid.y, np.sqrt(outline.area)),
    )  # fmt: skip
    return Building(
        "", Surface(vertices, triangles), lod="2.2", footprint=outline, roof_type=kind,
        planes=planes_used, plane_areas=areas, base_z=base,
        eave_z=float(eave_z.min() if len(eave_z) else roof_z.min()), ridge_z=float(roof_z.max()),
        watertight=is_watertight(vertices, triangles),
    )  # fmt: skip


def _watertight(b: Building) -> bool:
    return bool(b.watertight)

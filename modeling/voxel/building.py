"""The voxel path per building: proxy (section 4), then surface graph cuts (section 5).

Plain functions over the scene's cameras and images; :mod:`.path` reads the inputs and
runs them for every building.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree
from shapely.geometry import Polygon

from workbench.camera import Camera, framing_cameras
from workbench.model_run import Building
from workbench.raster import Grid
from workbench.records import peak_memory_mb
from workbench.texture_seams import ViewSamples, seam_cost, seen_views

from .options import VoxelOptions
from .proxy import (
    VoxelFrame,
    cluster_heights,
    column_minimum,
    consensus_levels,
    consistent_band,
    ellipsoid_normals,
    filter_levels,
    fused_fine_heights,
    fused_flat_levels,
    fused_floating_levels,
    fused_ground_columns,
    fused_roof_columns,
    fused_upper_levels,
    height_weighted_variance,
    highest_tied,
    occupancy,
    proxy_mesh,
    surface_normals,
    upward_views,
    variance_outliers,
    voxel_variance,
    voxelise,
)
from .roof_planes import RoofFaces, column_medians, roof_faces
from .surface_graph import (
    Stitching,
    SurfaceGraph,
    best_views,
    count_patches,
    refine_seams,
    select_views,
    stitch_patches,
    surface_graph,
    texel_colours,
    view_facing,
)
from .texture_atlas import atlas
from .view_images import ViewImages

PITCHED_SIMPLIFY_CELLS = 2.25  # as the super-pixel path's roofs, in fine cells


@dataclass
class Proxy:
    """The volumetric proxy of one building.

    Attributes
    ----------
    id : str
    frame : VoxelFrame
    columns : (nx, ny) bool
        Columns of the grown footprint.
    variance : ((nx, nz) float, (nx, ny) float)
        m_i of eq. 3 (NaN outside the columns or where unseen) on two slices, for the
        preview: the vertical one through the middle row of columns, and the horizontal
        one at the roof's top (:func:`variance_slices`). The volume is not kept: with
        the exterior's normals as volumes, it was most of a city's proxies.
    min_height : (nx, ny) float
        Height above the ground of each column's most consistent voxel (the highest
        tied with its minimum, :func:`highest_tied`), metres (NaN outside or discarded).
    levels : (nx, ny) int
        Filtered roof levels (0 empty); level l stands at ``level_heights[l - 1]``.
    level_heights : (K,) float
        Roof heights above ``frame.base_z``, metres.
    roof : RoofFaces
        The roof's faces and planes (the levels' flat planes, or pitched planes).
    exterior, normals : (N, 3) int, (N, 3) float
        The exterior voxels' indices (i, j, k) and their eq. 4 normals (local axes).
    model : Building or None
        The proxy's closed mesh with its footprint, roof planes and roof type, world
        metres (None when the proxy is empty).
    vertices, triangles : mesh of the proxy, world metres
    outline : Polygon or None
    record : dict
        What model.json says about it.
    """

    id: str
    frame: VoxelFrame
    columns: np.ndarray
    variance: np.ndarray
    min_height: np.ndarray
    levels: np.ndarray
    level_heights: np.ndarray
    roof: RoofFaces
    exterior: np.ndarray
    normals: np.ndarray
    model: Building | None
    record: dict = field(default_factory=dict)

    @property
    def vertices(self) -> np.ndarray:
        return self.model.mesh.vertices if self.model else np.zeros((0, 3))

    @property
    def triangles(self) -> np.ndarray:
        return self.model.mesh.triangles if self.model else np.zeros((0, 3), np.int64)

    @property
    def outline(self) -> Polygon | None:
        return self.model.footprint if self.model else None

    @property
    def empty(self) -> bool:
        return len(self.triangles) == 0

    def exterior_voxels_world(self) -> tuple[np.ndarray, np.ndarray]:
        """World centres (N, 3) and world unit normals (N, 3) of the exterior voxels."""
        i, j, k = self.exterior.T
        f = self.frame
        local = np.column_stack([f.x0 + (i + 0.5) * f.r, f.y0 + (j + 0.5) * f.r])
        centres = np.column_stack([f.to_world_xy(local), f.base_z + k * f.r])
        n = self.normals
        world = np.column_stack([n[:, :2] @ f.axes, n[:, 2]])
        return centres, world


def building_proxy(
    building_id: str,
    footprint: Polygon,
    height: float,
    base_z: float,
    cameras: list[Camera],
    images: ViewImages,
    options: VoxelOptions,
    occluders=None,
    fused_ndsm: tuple[np.ndarray, Grid] | None = None,
) -> Proxy:
    """Section 4 for one building: voxels, photo-consistency, height clusters, mesh.

    Parameters
    ----------
    footprint : Polygon
        GIS footprint, world metres.
    height : float
        Over-estimated height above ``base_z``, metres.
    base_z : float
        Ground height under the building, metres.
    occluders : workbench.raycast.RayScene, optional
        Initial proxies of the neighbouring buildings.
    fused_ndsm : (ndsm, grid), optional
        A fusion run's nDSM (H, W) metres and its grid: where it says ground, a column is
        ground (with ``options.fusion_ground``).
    """
    times = {}
    t0 = time.perf_counter()
    r = options.voxel_m
    frame, columns = voxelise(footprint, height, base_z, r, options.grow_m)
    nx, ny, nz = frame.shape
    centres = frame.voxel_centres(columns)
    normals = ellipsoid_normals(frame, columns)
    times["voxelise"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    pc, m = column_variance(centres, normals, nz, cameras, images, options, occluders)
    times["variance"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    layer, value = column_minimum(m)
    discarded = variance_outliers(value, options.outlier_sigma)
    on_fused_ground = np.zeros(len(value), bool)
    fine = fused_fine_heights(frame, *fused_ndsm) if fused_ndsm is not None else None
    fused = column_medians(fine, (nx, ny)) if fine is not None else None
    if fused is not None and options.fusion_ground:
        ground = fused_ground_columns(fused, options.min_height_m)
        on_fused_ground = ground[columns] & ~discarded
        discarded |= on_fused_ground
    # the run around the highest tied voxel, measured from that voxel's m_i
    layer = highest_tied(m, layer, options.tie_tolerance)
    lo, hi = consistent_band(m, layer, options.band_tolerance)
    heights = (lo + hi) / 2.0 * r  # the middle of the consistent run: steadier than the minimum
    variance = np.full((nx, ny, nz), np.nan)
    variance[columns] = m
    min_height = np.full((nx, ny), np.nan)
    min_height[columns] = np.where(discarded, np.nan, layer * r)
    levels, level_heights, photo_heights, n_clusters = roof_levels(
        heights, lo, hi, ~discarded, columns, nz, fused, options
    )
    times["clustering"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    roof = pitched_roof(frame, levels, level_heights, fine, options)
    times["roof_planes"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    occ = occupancy(roof.column_tops(r, frame.x0, frame.y0), r, nz)
    exterior, surf_normals = surface_normals(occ, options.normal_sigma)
    tolerance = options.simplify_m
    if tolerance is None:  # a staircase of fine cells along a hip is no edge of the roof
        tolerance = PITCHED_SIMPLIFY_CELLS * r / roof.k if roof.pitched else r / 4
    model = proxy_mesh(frame, roof, tolerance)
    times["mesh"] = time.perf_counter() - t0

    used = np.unique(levels[levels > 0])
    record = {
        "id": building_id,
        "gis_height_m": round(float(height), 3),
        "base_z": round(float(base_z), 3),
        "roof_heights_m": [round(float(level_heights[u - 1]), 3) for u in used],
        "roof_heights_photo_m": [round(float(h), 3) for h in photo_heights],
        "height_clusters": n_clusters,
        "pitched_planes": int(len(roof.planes)) if roof.pitched else 0,
        "voxels": int(columns.sum() * nz),
        "voxel_grid": [nx, ny, nz],
        "columns": int(columns.sum()),
        "columns_discarded": int(discarded.sum()),
        "columns_on_fused_ground": int(on_fused_ground.sum()),
        "proxy_columns": int((levels > 0).sum()),
        "occluded_samples": pc.occluded_samples,
        "faces": int(len(model.mesh.triangles)) if model else 0,
        "times_s": {k: round(v, 3) for k, v in times.items()},
        "peak_memory_mb": round(peak_memory_mb(), 1),
    }
    outside = np.argwhere(exterior)
    return Proxy(
        building_id, frame, columns, variance_slices(variance, frame, roof), min_height,
        levels, level_heights, roof, outside, surf_normals[tuple(outside.T)], model, record,
    )  # fmt: skip


def variance_slices(
    variance: np.ndarray, frame: VoxelFrame, roof: RoofFaces
) -> tuple[np.ndarray, np.ndarray]:
    """The proxy's ``variance`` (nx, ny, nz) on its vertical slice through the middle row
    of columns (nx, nz) and its horizontal slice at the roof's top (nx, ny)."""
    nx, ny, nz = frame.shape
    tops = roof.column_tops(frame.r, frame.x0, frame.y0)
    roof_top = float(tops.max()) if np.isfinite(tops).any() else 0.0
    k = min(nz - 1, max(0, int(round(roof_top / frame.r))))
    return variance[:, ny // 2, :].copy(), variance[:, :, k].copy()


def pitched_roof(
    frame: VoxelFrame,
    levels: np.ndarray,
    level_heights: np.ndarray,
    fine: np.ndarray | None,
    options: VoxelOptions,
) -> RoofFaces:
    """The proxy's roof faces: planes where the levels leave a high error
    (:func:`~modeling.voxel.roof_planes.roof_faces`), fitted to the fusion's heights
    ``fine`` (k x k per column, metres). Without a fusion run the levels stay: the
    photo-consistent heights, a voxel apart and with gross errors, gave planes that put
    the `tiny` city's roofs 43 % off in height (median; 4.8 % as levels)."""
    if fine is None or not options.pitched_roofs:
        fine = np.full(levels.shape, np.nan)
    return roof_faces(
        levels, level_heights, fine, frame.r, frame.x0, frame.y0,
        tolerance=options.plane_tolerance_m, gain=options.plane_gain,
        min_points=max(3, int(np.ceil(options.min_plane_m2 / frame.r**2))),
        min_height=options.min_height_m, seed=options.seed,
    )  # fmt: skip


def column_variance(
    centres: np.ndarray,
    normals: np.ndarray,
    nz: int,
    cameras: list[Camera],
    images: ViewImages,
    options: VoxelOptions,
    occluders=None,
):
    """Eq. 2-3: each voxel's photo-consistency (variance of the colours its views see),
    unknown where too few views see it, weighted by height.

    Returns
    -------
    the voxels' samples (:func:`~modeling.voxel.proxy.voxel_variance`) and (C, nz) m_i of
    every column's voxels.
    """
    r = options.voxel_m
    views = framing_cameras(cameras, centres.reshape(-1, 3))

    def sample(c: np.ndarray, n: np.ndarray):
        return voxel_variance(
            c, n, r, cameras, images, occluders, options.footprint_scale, options.keep_views,
            views,
        )  # fmt: skip

    pc = sample(centres.reshape(-1, 3), normals.reshape(-1, 3))
    # a variance from a few views is small by chance: voxels high above the building,
    # which most views frame out, would win every column
    seen = pc.views[pc.views > 0]
    min_views = max(3.0, options.min_view_fraction * np.median(seen)) if len(seen) else 3.0
    pc = upward_views(pc, centres.reshape(-1, 3), min_views, sample)
    m = height_weighted_variance(
        np.where(pc.views >= min_views, pc.variance, np.nan).reshape(-1, nz),
        np.arange(nz),
        nz,
        options.height_weight,
    )
    return pc, m


def roof_levels(
    heights: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    usable: np.ndarray,
    columns: np.ndarray,
    nz: int,
    fused: np.ndarray | None,
    options: VoxelOptions,
):
    """Section 4.3: the columns' consistent heights clustered into roof levels (1D
    k-means, c_e), filtered, and with a fusion run those floating above its nDSM emptied
    and the flat ones placed on it.

    Parameters
    ----------
    heights, lo, hi : (C,) the middle of each column's consistent run, metres, and the
        run's bounds, voxels; usable : (C,) bool columns kept; columns : (nx, ny) bool.

    Returns
    -------
    levels (nx, ny) int (0 empty), level_heights (K,) metres above the base, the
    photo-consistent heights of the levels used, and the number of height clusters.
    """
    r = options.voxel_m
    levels = np.zeros(columns.shape, np.int64)
    kept = np.flatnonzero(usable)
    if not len(kept):
        return levels, np.zeros(0), np.zeros(0), 0
    # the ground is one group; k-means sorts the roofs (c_e then weighs roof levels
    # against each other, not against the ground's far larger step)
    on_roof = heights[kept] >= options.min_height_m
    labels = np.zeros(len(kept), np.int64)
    if on_roof.any():
        roof_labels, _ = cluster_heights(
            heights[kept][on_roof], options.cluster_error, seed=options.seed
        )
        labels[on_roof] = roof_labels + 1
    n_clusters = int(labels.max()) + 1
    labels, layers = consensus_levels(lo[kept], hi[kept], labels, n_clusters, nz)
    means = layers * r
    roof = means >= options.min_height_m
    rank = np.cumsum(roof) * roof  # 0 for ground levels, 1.. for roofs
    level_heights = means[roof]
    col_levels = np.zeros(len(heights), np.int64)
    col_levels[kept] = rank[labels]
    levels[columns] = col_levels
    levels = filter_levels(levels, columns)
    photo_heights = level_heights[np.unique(levels[levels > 0]) - 1]
    if fused is not None:
        levels = fused_floating_levels(levels, level_heights, fused, 0.5 * r, 1.5 * r)
    if fused is not None and options.fusion_flat_roofs:
        levels, level_heights = fused_flat_levels(
            levels, level_heights, fused, columns, 0.5 * r, 1.5 * r
        )
        levels, level_heights = fused_upper_levels(levels, level_heights, fused, 0.5 * r, 1.5 * r)
    if fused is not None and options.pitched_roofs:
        levels = fused_roof_columns(levels, level_heights, fused, columns, options.min_height_m)
    return levels, level_heights, photo_heights, n_clusters


@dataclass
class Texture:
    """The surface graph cut texture of one building (section 5.2).

    Attributes
    ----------
    graph : SurfaceGraph
    samples : ViewSamples
    initial : (V,) int
        Each vertex's best view, where the stitching starts.
    projective : (V,) int
        Naive projective texture mapping: every voxel face from its best view.
    stitched : Stitching
        After the graph cuts.
    image : (H, W, 3) uint8
        The atlas.
    uvs : (T, 3, 2) float
        Texture coordinates of the proxy's triangle corners.
    record : dict
    views : (K,) int
        The camera of each column of ``samples``: the labels above index these columns.
    """

    graph: SurfaceGraph
    samples: ViewSamples
    initial: np.ndarray
    projective: np.ndarray
    stitched: Stitching
    image: np.ndarray
    uvs: np.ndarray
    record: dict
    views: np.ndarray

    def colours(self, labels: np.ndarray | None = None) -> np.ndarray:
        """(V, 3) uint8 texel colours under ``labels`` (default: the stitched views)."""
        return texel_colours(self.stitched.labels if labels is None else labels, self.samples)


def texture_building(
    proxy: Proxy,
    cameras: list[Camera],
    images: ViewImages,
    options: VoxelOptions,
    occluders=None,
    vertices: np.ndarray | None = None,
    triangles: np.ndarray | None = None,
) -> Texture:
    """Surface graph, best views, greedy graph-cut stitching and atlas of one proxy
    (or of ``vertices``/``triangles`` standing in for its mesh, e.g. a perturbed one).

    Parameters
    ----------
    occluders : workbench.raycast.RayScene, optional
        All proxies of the scene, for visibility.
    """
    t0 = time.perf_counter()
    V = proxy.vertices if vertices is None else vertices
    T = proxy.triangles if triangles is None else triangles
    texel = options.voxel_m / options.subdivisions
    u_hint = np.array([*proxy.frame.axes[0], 0.0])
    graph = surface_graph(V, T, texel, u_hint)
    t_graph = time.perf_counter() - t0

    t0 = time.perf_counter()
    smooth = _voxel_normals_at(proxy, graph.positions, graph.normals)
    framing = framing_cameras(cameras, V)
    chosen = select_views(graph.positions, graph.normals, smooth, cameras, framing, occluders,
                          options.view_tolerance)  # fmt: skip
    views, samples = seen_views(graph.positions, graph.normals, cameras, images, occluders, chosen)
    best = best_views(graph.positions, smooth, [cameras[k].center for k in views], samples)
    projective = face_views(voxel_faces(proxy.frame, graph), best, samples)
    t_views = time.perf_counter() - t0

    t0 = time.perf_counter()
    stitched = stitch_patches(graph.edges, graph.positions, best, samples, options.overlap_m)
    t_cut = time.perf_counter() - t0
    cost_greedy, _ = seam_cost(graph.edges, stitched.labels, samples)
    t0 = time.perf_counter()
    if options.refine_sweeps > 0:
        refined = refine_seams(
            graph.edges, stitched.labels, samples, options.facing_weight, options.refine_sweeps
        )
        stitched = replace(
            stitched, labels=refined, patches_after=count_patches(graph.edges, refined)
        )
    t_refine = time.perf_counter() - t0
    cost_cut, seams_cut = seam_cost(graph.edges, stitched.labels, samples)
    cost_proj, seams_proj = seam_cost(graph.edges, projective, samples)

    t0 = time.perf_counter()
    image, uvs = atlas(graph, texel_colours(stitched.labels, samples), V, T)
    t_atlas = time.perf_counter() - t0
    used = np.unique(stitched.labels[stitched.labels >= 0])
    record = {
        "graph_vertices": int(len(graph.positions)),
        "graph_edges": int(len(graph.edges)),
        "charts": len(graph.charts),
        "unseen_vertices": int((projective < 0).sum()),
        "patches_before": stitched.patches_before,
        "patches_after": stitched.patches_after,
        "cuts": stitched.cuts,
        "views_framing": len(framing),
        "views_chosen": len(chosen),
        "views_used": int(len(used)),
        "seam_cost": round(cost_cut, 4),
        "seam_cost_projective": round(cost_proj, 4),
        "seam_cost_greedy": round(cost_greedy, 4),
        "seam_edges": seams_cut,
        "seam_edges_projective": seams_proj,
        "view_facing": round(view_facing(stitched.labels, samples), 4),
        "view_facing_projective": round(view_facing(projective, samples), 4),
        "atlas_px": [int(image.shape[1]), int(image.shape[0])],
        "times_s": {
            "surface_graph": round(t_graph, 3),
            "visibility": round(t_views, 3),
            "graph_cuts": round(t_cut, 3),
            "refine_seams": round(t_refine, 3),
            "atlas": round(t_atlas, 3),
        },
    }
    return Texture(graph, samples, best, projective, stitched, image, uvs, record,
                   np.asarray(views, int))  # fmt: skip


def voxel_faces(frame: VoxelFrame, graph: SurfaceGraph) -> np.ndarray:
    """(V,) id of the voxel face each texel lies on (its chart and its voxel cell on it)."""
    if not len(graph.positions):
        return np.zeros(0, np.int64)
    local = frame.to_local_xy(graph.positions[:, :2])
    cell = np.floor((local - [frame.x0, frame.y0]) / frame.r).astype(np.int64)
    layer = np.floor((graph.positions[:, 2] - frame.base_z) / frame.r).astype(np.int64)
    roof = np.abs(graph.normals[:, 2]) > 0.9
    n_local = graph.normals[:, :2] @ frame.axes.T
    along = np.where(np.abs(n_local[:, 0]) > np.abs(n_local[:, 1]), cell[:, 1], cell[:, 0])
    key = np.column_stack(
        [graph.chart, np.where(roof, cell[:, 0], along), np.where(roof, cell[:, 1], layer)]
    )
    return np.unique(key, axis=0, return_inverse=True)[1].ravel()


def face_views(faces: np.ndarray, best: np.ndarray, samples: ViewSamples) -> np.ndarray:
    """Projective texture mapping: each voxel face takes the view most of its texels
    rate best, where that view sees them (elsewhere a texel keeps its own best view)."""
    out = best.copy()
    seen = best >= 0
    if not seen.any():
        return out
    k = samples.visible.shape[1]
    votes = np.zeros((faces.max() + 1, k), np.int64)
    np.add.at(votes, (faces[seen], best[seen]), 1)
    choice = votes.argmax(axis=1)[faces]
    ok = seen & samples.visible[np.arange(len(best)), choice]
    out[ok] = choice[ok]
    return out


def _voxel_normals_at(proxy: Proxy, positions: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """n_a: the eq. 4 normal of the exterior voxel nearest each graph vertex."""
    centres, normals = proxy.exterior_voxels_world()
    if not len(centres) or not len(positions):
        return fallback
    _, nearest = cKDTree(centres).query(positions)
    n = normals[nearest]
    bad = np.linalg.norm(n, axis=1) < 0.5
    n[bad] = fallback[bad]
    return n

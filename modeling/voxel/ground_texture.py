"""The ground's texture (the voxel paper, sections 5.3 and 5.4).

The ground cut stitches a top-down texture from the most downward-looking views with the
building proxies masked out: a ground texel hidden behind a proxy in a view cannot take
that view, so no building is painted on the street. The building-ground ring cut then
lets each building's wall views continue onto the ground around it, up to the smoothest
seam, within a ring of configurable width.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from workbench.camera import Camera, framing_cameras
from workbench.graph_cuts import binary_cut, grid_pairs
from workbench.meshes import raster_mesh
from workbench.raster import Grid
from workbench.texture_seams import (
    ViewSamples,
    rgb_to_lab,
    seam_cost,
    seam_costs,
    seen_views,
    view_samples,
)

from .surface_graph import best_views, stitch_patches, texel_colours
from .view_images import ViewImages

_INF = 1e9
_NADIR_SPREAD_DEG = 15.0


def downward_views(cameras: list[Camera], spread_deg: float = _NADIR_SPREAD_DEG) -> list[int]:
    """The views whose optical axis is within ``spread_deg`` of the most downward one."""
    tilt = np.degrees(np.arccos(np.clip([-c.viewing_direction[2] for c in cameras], -1, 1)))
    return [int(k) for k in np.flatnonzero(tilt <= tilt.min() + spread_deg)]


@dataclass
class GroundTexture:
    """A top-down ground texture, or a window of it.

    Attributes
    ----------
    grid : Grid
    z : (H, W) float or None
        Ground height of every texel, metres (None where only the image is needed).
    image : (H, W, 3) uint8
    """

    grid: Grid
    z: np.ndarray | None
    image: np.ndarray


@dataclass
class GroundTile:
    """One tile's ground cut: its image (h, w, 3) uint8, labels (h, w) (scene views, -1
    unseen), and the figures the record sums: texels, unseen texels, graph edges,
    patches before and after, and the seam costs summed over the edges."""

    image: np.ndarray
    labels: np.ndarray
    counts: dict


def ground_cut(
    grid: Grid,
    z: np.ndarray,
    cameras: list[Camera],
    images: ViewImages,
    occluders,
    overlap_m: float,
) -> GroundTile:
    """The ground surface graph cut (section 5.4) on the texels of ``grid`` (the whole
    ground, or one tile of it).

    Parameters
    ----------
    grid : Grid
        Texel grid of the ground, metres.
    z : (H, W) float
        Ground height at the texel centres, metres.
    occluders : workbench.raycast.RayScene
        All building proxies: the masks of the paper.
    overlap_m : float
        Band width of the stitching cuts, metres.
    """
    X, Y = grid.cell_centers()
    positions = np.column_stack([X.ravel(), Y.ravel(), z.ravel()])
    up = np.broadcast_to([0.0, 0.0, 1.0], positions.shape)
    down = downward_views(cameras)
    views = [down[j] for j in framing_cameras([cameras[k] for k in down], positions)]
    if not views:  # a tile beyond every downward view (off the flight): nothing to cut
        n = len(positions)
        return GroundTile(np.zeros((grid.height, grid.width, 3), np.uint8),
                          np.full(grid.shape, -1), {"texels": n, "unseen": n})  # fmt: skip
    views, samples = seen_views(positions, up, cameras, images, occluders, views)
    centres = np.array([cameras[k].center for k in views]).reshape(-1, 3)
    labels = best_views(positions, up, centres, samples)
    edges, _ = grid_pairs(grid.shape)
    stitched = stitch_patches(edges, positions, labels, samples, overlap_m, min_patch=64)
    cost_cut, _ = seam_cost(edges, stitched.labels, samples)
    cost_proj, _ = seam_cost(edges, labels, samples)
    image = texel_colours(stitched.labels, samples).reshape(grid.height, grid.width, 3)
    image = fill_unseen(image, stitched.labels.reshape(grid.shape))
    scene_views = np.asarray(views + [-1], int)[stitched.labels]  # -1 stays -1
    counts = {
        "texels": int(len(positions)), "unseen": int((labels < 0).sum()),
        "edges": int(len(edges)), "patches_before": stitched.patches_before,
        "patches_after": stitched.patches_after, "seam_cost_sum": cost_cut * len(edges),
        "seam_cost_projective_sum": cost_proj * len(edges),
    }  # fmt: skip
    return GroundTile(image, scene_views.reshape(grid.shape), counts)


def ground_record(grid: Grid, counts: list[dict]) -> dict:
    """The ground's record from its tiles' cuts' ``counts`` (:class:`GroundTile`, with the
    scene views each used under "views"): seam costs per graph edge over all tiles (the
    tiles' borders are seams the cuts did not place)."""
    total: dict = {}
    views: set[int] = set()
    for c in counts:
        views.update(c.get("views", []))
        for k, v in c.items():
            if k != "views":
                total[k] = total.get(k, 0) + v
    edges = max(total.get("edges", 0), 1)
    return {
        "texels": [grid.width, grid.height],
        "texel_m": grid.gsd,
        "tiles": len(counts),
        "views": sorted(int(k) for k in views),
        "unseen_fraction": round(total.get("unseen", 0) / max(total.get("texels", 0), 1), 4),
        "patches_before": total.get("patches_before", 0),
        "patches_after": total.get("patches_after", 0),
        "seam_cost": round(total.get("seam_cost_sum", 0.0) / edges, 4),
        "seam_cost_projective": round(total.get("seam_cost_projective_sum", 0.0) / edges, 4),
    }


GROUND_MESH_M = 4.0  # the ground mesh's quads, metres


def ground_mesh_step(gsd: float, spacing_m: float = GROUND_MESH_M) -> int:
    """Texels between the ground mesh's vertices."""
    return max(1, round(spacing_m / gsd))


def ground_mesh(
    ground: GroundTexture, spacing_m: float = GROUND_MESH_M
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The textured ground: the ground heights in quads of about ``spacing_m`` metres,
    through every :func:`ground_mesh_step`-th texel centre of ``ground.grid``.

    Returns
    -------
    vertices : (V, 3), triangles : (T, 3), uvs : (T, 3, 2) into ``ground.image``
    (u east, v north, 0-1); None when the grid is too small.
    """
    mesh = raster_mesh(ground.z, ground.grid, step=ground_mesh_step(ground.grid.gsd, spacing_m))
    if mesh is None:
        return None
    vertices, triangles = mesh
    xmin, ymin, xmax, ymax = ground.grid.bounds
    uv = np.column_stack(
        [(vertices[:, 0] - xmin) / (xmax - xmin), (vertices[:, 1] - ymin) / (ymax - ymin)]
    )
    return vertices, triangles, uv[triangles]


def fill_unseen(image: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Texels no view sees (under buildings) take the nearest seen texel's colour."""
    unseen = labels < 0
    if not unseen.any() or unseen.all():
        return image
    idx = ndimage.distance_transform_edt(unseen, return_distances=False, return_indices=True)
    return image[idx[0], idx[1]]


@dataclass
class RingSamples:
    """The building's side of a ring cut (section 5.3), which does not depend on the
    ground's texture: sampled where the views are (a task), cut where the texture is.

    Attributes
    ----------
    ring : (H, W) bool
        The ring's texels in the building's window of the ground grid.
    dist : (N,) float
        Each ring texel's distance to the footprint, metres.
    lab : (N, 3) float32
        CIE Lab of each ring texel in the view of its nearest bottom-wall texel.
    rgb : (N, 3) uint8
        The same colour, RGB.
    seen : (N,) bool
        Whether that view sees the texel.
    """

    ring: np.ndarray
    dist: np.ndarray
    lab: np.ndarray
    rgb: np.ndarray
    seen: np.ndarray


def ring_samples(
    grid: Grid,
    z: np.ndarray,
    footprint: np.ndarray,
    wall_view: np.ndarray,
    cameras: list[Camera],
    images: ViewImages,
    occluders,
    ring_m: float,
) -> RingSamples:
    """The ring around a building and its wall views' colours on it.

    Parameters
    ----------
    grid : Grid
        A window of the ground grid around the building.
    z : (H, W) float
        The ground's height on ``grid``, metres.
    footprint : (H, W) bool
        The building's proxy footprint on ``grid``.
    wall_view : (H, W) int
        For every texel, the scene view of the nearest bottom-wall texel of the building
        (-1 none).
    ring_m : float
        Ring width, metres.
    """
    dist = ndimage.distance_transform_edt(~footprint) * grid.gsd
    ring = (dist > 0) & (dist <= ring_m) & (wall_view >= 0)
    n = int(ring.sum())
    X, Y = grid.cell_centers()
    positions = np.column_stack([X[ring], Y[ring], z[ring]])
    up = np.broadcast_to([0.0, 0.0, 1.0], positions.shape)
    lab = np.zeros((n, 3), np.float32)
    rgb = np.zeros((n, 3), np.uint8)
    seen = np.zeros(n, bool)
    views = wall_view[ring]
    for k in np.unique(views):
        sel = views == k
        s = view_samples(positions[sel], up[sel], cameras, images, occluders, [int(k)])
        lab[sel] = s.lab[:, 0]
        rgb[sel] = s.rgb[:, 0]
        seen[sel] = s.visible[:, 0]
    return RingSamples(ring, dist[ring], lab, rgb, seen)


def ring_cut(ground: GroundTexture, samples: RingSamples, ring_m: float) -> dict:
    """The building-ground surface graph cut (section 5.3), in place on ``ground.image``.

    Parameters
    ----------
    ground : GroundTexture
        The window of the ground texture ``samples`` were taken on.
    samples : RingSamples
    ring_m : float
        Ring width, metres.

    Returns
    -------
    dict with the ring's texel count and how many took the building's views.
    """
    ring, seen = samples.ring, samples.seen
    if not ring.any():
        return {"ring_texels": 0, "from_building": 0}
    gsd = ground.grid.gsd
    rows, cols = np.nonzero(ring)
    ground_rgb = ground.image[ring].astype(np.float32)
    both = ViewSamples(
        visible=np.column_stack([seen, np.ones(len(rows), bool)]),
        facing=np.ones((len(rows), 2), np.float32),
        lab=np.stack([samples.lab, rgb_to_lab(ground_rgb)], axis=1),
        rgb=np.stack([samples.rgb, ground.image[ring]], axis=1),
    )
    index = np.full(ground.grid.shape, -1)
    index[ring] = np.arange(len(rows))
    edges, _ = grid_pairs(ground.grid.shape)
    a, b = index.ravel()[edges[:, 0]], index.ravel()[edges[:, 1]]
    keep = (a >= 0) & (b >= 0)
    e = np.column_stack([a[keep], b[keep]])
    weights = seam_costs(e, np.zeros(len(e), int), np.ones(len(e), int), both)
    d = samples.dist
    unary = np.zeros((len(rows), 2))
    # the first row joins the footprint (the source): a seam right at the wall costs what
    # the two colourings differ there, as any other edge of the graph
    step = np.linalg.norm(both.lab[:, 0] - both.lab[:, 1], axis=1)
    unary[:, 1] = np.where(d <= 1.5 * gsd, np.where(seen, 2 * step, 0.0), 0.0)
    unary[:, 0] = np.where((d > ring_m - 1.5 * gsd) | ~seen, _INF, 0.0)  # outer edge: ground
    side = binary_cut(unary, e, weights, 1.0)
    take = side == 0
    ground.image[rows[take], cols[take]] = samples.rgb[take]
    return {"ring_texels": int(len(rows)), "from_building": int(take.sum())}

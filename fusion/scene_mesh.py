"""A coloured surface mesh of a scene from its calibrated views and depth maps: what a
user's MVS tool gives (dense, noisy, its corners rounded), for the LOD path and as an
export.

Each view's depth map and image are integrated into a truncated signed distance field
(Open3D's voxel block grid, hashed blocks of 8³ voxels), and marching cubes extracts its
zero level. Depth pixels that land outside the scene's bounds are left out: oblique views
see the terrain hundreds of metres beyond the area of interest, and every block they
touch costs memory. Open3D works in float32: the views are moved to a local origin (the
bounds' centre, to the kilometre) and the mesh moved back in float64.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import open3d.core as o3c

from workbench.errors import InputError, WorkbenchError
from workbench.progress import progress
from workbench.scene import Scene

from .scene_fusion import physical_memory

log = logging.getLogger(__name__)

BLOCK_VOXELS = 8  # voxels along a block's side
BLOCK_BYTES = BLOCK_VOXELS**3 * 5 * 4  # tsdf, weight and colour (3) as float32
BLOCKS_PER_COLUMN = 8  # measured on `small`: ground, roofs, walls and noise
PEAK_FACTOR = 2.5  # the hash map's growth and the extraction, over the blocks themselves


@dataclass
class SceneMesh:
    """A coloured triangle mesh in world metres.

    Attributes
    ----------
    vertices : (V, 3) float64
    triangles : (T, 3) int64, counter-clockwise seen from outside (the camera's side)
    colors : (V, 3) uint8
    record : dict
        Voxel size, truncation, views, blocks, times.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    colors: np.ndarray
    record: dict


def integrate_views(
    scene: Scene,
    voxel_m: float | None = None,
    trunc_voxels: float = 4.0,
    bounds: tuple[float, float, float, float] | None = None,
    min_weight: float = 1.0,
    max_memory_fraction: float = 0.6,
) -> SceneMesh:
    """TSDF integration of every view's depth map and colour, then marching cubes.

    Parameters
    ----------
    scene : Scene
        Calibrated views with depth maps (z-depth, metres, NaN unknown).
    voxel_m : float, optional
        Voxel edge, metres (default: the scene's gsd, else 0.25).
    trunc_voxels : float
        Truncation of the signed distance, in voxels.
    bounds : (xmin, ymin, xmax, ymax), optional
        Area meshed (default: the scene's bounds; else all the views see).
    min_weight : float
        Voxels seen by fewer views' worth of weight are left out of the surface.
    max_memory_fraction : float
        Refuse, before integrating, an area whose blocks would need more of the
        machine's memory than this.

    Raises
    ------
    InputError
        A view has no depth map.
    WorkbenchError
        The area would not fit in memory at this voxel size.
    """
    voxel_m = float(voxel_m or scene.gsd or 0.25)
    bounds = bounds or scene.bounds
    for v in scene.views:
        if v.depth_path is None:
            raise InputError(v.image_path, "depth", "mesh: every view needs a depth map")
    if bounds is not None:
        columns = (bounds[2] - bounds[0]) * (bounds[3] - bounds[1]) / (BLOCK_VOXELS * voxel_m) ** 2
        need = columns * BLOCKS_PER_COLUMN * BLOCK_BYTES * PEAK_FACTOR
        if need > max_memory_fraction * physical_memory():
            raise WorkbenchError(
                f"mesh: --voxel {voxel_m:g} over {bounds} needs about {need / 2**30:.1f} GiB, "
                f"more than {max_memory_fraction:.0%} of this machine's "
                f"{physical_memory() / 2**30:.0f} GiB; use a larger --voxel or smaller --bounds"
            )
        centre = np.array([(bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2, 0.0])
        blocks = int(columns * BLOCKS_PER_COLUMN) + 1000
    else:
        centre = np.mean([v.camera.center for v in scene.views], axis=0) * [1, 1, 0]
        blocks = 100_000
    origin = np.round(centre / 1000.0) * 1000.0
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=voxel_m,
        block_resolution=BLOCK_VOXELS,
        block_count=blocks,
        device=o3c.Device("CPU:0"),
    )
    depth_max = 0.0
    for view in progress(scene.views, "mesh: integrating views"):
        image, depth = undistorted(view)
        depth = in_bounds(depth, view.camera, bounds)
        if not (depth > 0).any():
            continue
        depth_max = max(depth_max, float(depth.max()))
        K = o3c.Tensor(view.camera.K, o3c.float64)
        E = o3c.Tensor(local_extrinsic(view.camera, origin), o3c.float64)
        d_img = o3d.t.geometry.Image(o3c.Tensor(depth))
        c_img = o3d.t.geometry.Image(o3c.Tensor(image.astype(np.float32) / 255.0))
        far = float(depth.max()) + 1.0
        coords = grid.compute_unique_block_coordinates(
            d_img, K, E, 1.0, far, trunc_voxel_multiplier=trunc_voxels
        )
        grid.integrate(coords, d_img, c_img, K, K, E, 1.0, far,
                       trunc_voxel_multiplier=trunc_voxels)  # fmt: skip
    mesh = grid.extract_triangle_mesh(weight_threshold=min_weight).to_legacy()
    order, triangles = canonical_order(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    vertices = np.asarray(mesh.vertices, np.float64)[order] + origin
    colors = np.asarray(mesh.vertex_colors)[order]
    colors = np.clip(colors * 255.0 + 0.5, 0, 255).astype(np.uint8)
    record = {
        "voxel_m": voxel_m, "trunc_m": round(trunc_voxels * voxel_m, 4),
        "bounds": list(bounds) if bounds is not None else None,
        "views": len(scene.views), "blocks": int(grid.hashmap().size()),
        "vertices": len(vertices), "triangles": len(triangles),
    }  # fmt: skip
    if not len(triangles):
        raise WorkbenchError("mesh: the views' depth maps gave no surface inside the bounds")
    return SceneMesh(vertices, triangles, colors, record)


def canonical_order(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The order of a mesh that depends on its geometry alone.

    Open3D integrates and extracts its voxel blocks in many threads, so the same surface
    comes out with its vertices and triangles in another order from run to run (seed 5
    of `small`: 3.2 M triangles, the same sets, the files different); where two triangles
    tie for a ray, the mesh's sampling then takes one or the other, and the LOD path's
    figures moved between runs of the same code (seed 2's 2D quality by 0.017, seed 4's
    roof types by 0.05). Vertices are
    sorted by position (x, then y, then z); each triangle is turned, keeping its winding,
    to start at its lowest vertex, and the triangles sorted.

    Parameters
    ----------
    vertices : (V, 3) float
    triangles : (T, 3) int

    Returns
    -------
    order : (V,) int64
        The vertices' new order: ``vertices[order]``.
    triangles : (T, 3) int64
        The triangles on the reordered vertices.
    """
    v = np.asarray(vertices)
    order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    t = rank[np.asarray(triangles, np.int64)]
    first = np.argmin(t, axis=1)
    t = t[np.arange(len(t))[:, None], (first[:, None] + np.arange(3)) % 3]
    return order, t[np.lexsort((t[:, 2], t[:, 1], t[:, 0]))]


def write_scene_mesh(path, mesh: SceneMesh, crs) -> None:
    """Write ``mesh`` as binary PLY (float64 positions, vertex colours, the CRS in a
    ``comment crs`` header line, which ``workbench fusion --mesh`` reads), whole or not
    at all: it is written beside ``path`` and moved into place."""
    from workbench.meshio import write_ply
    from workbench.model_run import crs_text

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial")
    write_ply(partial, mesh.vertices, mesh.triangles, vertex_colors=mesh.colors,
              comments=[f"crs {crs_text(crs)}"] if crs is not None else None)  # fmt: skip
    partial.replace(path)


def local_extrinsic(camera, origin: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera matrix of ``camera`` for points relative to ``origin``:
    x_cam = R (X_local + origin) + t."""
    E = np.eye(4)
    E[:3, :3] = camera.R
    E[:3, 3] = camera.t + camera.R @ origin
    return E


def undistorted(view) -> tuple[np.ndarray, np.ndarray]:
    """The view's image (H, W, 3) uint8 and z-depth (H, W) float32 (0 unknown) as a
    pinhole camera of the same K sees them (Open3D integrates without distortion)."""
    image = view.read_image()
    depth = np.ascontiguousarray(view.read_depth(), np.float32)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    c = view.camera
    if c.has_distortion:
        maps = cv2.initUndistortRectifyMap(c.K, c.distortion, None, c.K, (c.width, c.height),
                                           cv2.CV_32FC1)  # fmt: skip
        image = cv2.remap(image, *maps, cv2.INTER_LINEAR)
        depth = cv2.remap(depth, *maps, cv2.INTER_NEAREST)  # no depth between two surfaces
    return np.ascontiguousarray(image), np.ascontiguousarray(depth)


def in_bounds(depth: np.ndarray, camera, bounds) -> np.ndarray:
    """``depth`` (H, W) with 0 where its pixel's point lies outside ``bounds`` (world xmin,
    ymin, xmax, ymax; None keeps every pixel). ``depth`` is undistorted: its pixels are
    read through ``camera``'s pinhole."""
    if bounds is None:
        return depth
    pinhole = dataclasses.replace(camera, distortion=np.zeros(5))
    origin, dirs = pinhole.pixel_grid_rays()
    X = origin + dirs * depth.reshape(-1, 1)
    out = (
        (X[:, 0] < bounds[0])
        | (X[:, 0] > bounds[2])
        | (X[:, 1] < bounds[1])
        | (X[:, 1] > bounds[3])
    )
    return np.where(out.reshape(depth.shape), np.float32(0.0), depth)

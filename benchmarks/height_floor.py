"""What the height metrics can reach at all: the scores of noise-free sensors.

The truth DSM of a sample is the true surface read at each cell centre. A fused DSM
is a median over returns spread over the cell, and a model's wall is never exactly
where the truth's is; beside a wall either is a wall's height off. This script reads
the true mesh with vertical rays and scores, with the metrics of ``workbench compare``:

- the median of ``k`` returns at random places in each cell (a perfect, noise-free
  fusion of ``k`` observations per cell), against the truth DSM and over the true
  building cells (as the models' height RMSE is scored);
- the surface read at the cell centre displaced by ``d`` metres in a random direction
  (a perfect model whose walls are off by ``d``), over the true building cells;
- the cells whose true surface (at the centre or a quarter cell from it) some view sees
  at all, and those some view's depth map observes within 0.5 m: what the valid
  fraction of a fusion can reach without inventing cells;
- a perfect model whose outlines lie ``k`` cells inside the true ones (the footprints
  eroded by ``k`` cells, the ground there), over the true building cells and off the
  truth's height jumps: how far inside an outline may lie for a model to meet a height
  RMSE off the jumps (the issues' 0.5 and 0.6 m);
- the voxel path's height clustering (section 4.3 of the voxel paper) run on the true
  height of every 1 m column of the true footprints, each column snapped to its
  cluster's mean: the building height error of a perfect 2.5D proxy.

Usage: python benchmarks/height_floor.py SCENE [--returns 15] [--seed 0] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from modeling.voxel.proxy import cluster_heights, voxelise
from workbench import metrics
from workbench.footprints import read_footprints
from workbench.meshio import read_ply
from workbench.raster import Grid
from workbench.raycast import cast, raycasting_scene
from workbench.scene import load_scene
from workbench.truth import Truth, load_scene_truth

CLASS_TREE = 3  # the class property of the sample's truth mesh
DEPTH_AGREES_M = 0.5  # a depth map observes a point when it reads its depth this closely


def surface_at(scene, grid: Grid, origin: np.ndarray, top: float, dx, dy) -> np.ndarray:
    """(H, W) height of the mesh straight below each cell centre moved by (dx, dy) m,
    NaN where nothing is hit. ``scene`` holds the mesh shifted by ``-origin``."""
    X, Y = grid.cell_centers()
    x = (X + dx - origin[0]).ravel()
    y = (Y + dy - origin[1]).ravel()
    origins = np.column_stack([x, y, np.full(x.size, top)])
    hits = cast(scene, origins, np.tile([0.0, 0.0, -1.0], (x.size, 1)))
    return (hits.points[:, 2] + origin[2]).reshape(grid.shape)


def cells_seen(scene_dir: Path, grid: Grid, scene, origin: np.ndarray, top: float) -> dict:
    """Fractions of cells some view sees and some depth map observes.

    A cell is seen when the true surface at its centre or at one of the four points a
    quarter cell from it is inside some view's frame and not hidden from it by the
    true mesh (``seen_by_a_view``); observed when, at one of those points, some view's
    depth map reads the depth within ``DEPTH_AGREES_M`` (``observed_by_a_depth_map``).
    ``scene`` holds the true mesh shifted by ``-origin``; rays start at height ``top``.
    """
    q = grid.gsd / 4
    offsets = [(0.0, 0.0), (-q, -q), (-q, q), (q, -q), (q, q)]
    X, Y = grid.cell_centers()
    points = np.concatenate(
        [
            np.column_stack(
                [
                    (X + dx).ravel(),
                    (Y + dy).ravel(),
                    surface_at(scene, grid, origin, top, dx, dy).ravel(),
                ]
            )
            for dx, dy in offsets
        ]
    )
    known = np.isfinite(points[:, 2])
    seen = np.zeros(len(points), bool)
    observed = np.zeros(len(points), bool)
    for view in load_scene(scene_dir).views:
        cam = view.camera
        uv, depth = cam.project(points)
        with np.errstate(invalid="ignore"):
            framed = known & (depth > 0)
            framed &= (uv[:, 0] >= 0) & (uv[:, 0] < cam.width)
            framed &= (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        idx = np.flatnonzero(framed)
        to_cam = cam.center - points[idx]
        dist = np.linalg.norm(to_cam, axis=1)
        to_cam /= dist[:, None]
        # start a few centimetres off the surface, so that it does not hide itself
        hits = cast(scene, points[idx] - origin + 0.05 * to_cam, to_cam)
        idx = idx[~np.isfinite(hits.t) | (hits.t > dist - 0.1)]
        seen[idx] = True
        if view.depth_path is None:
            continue
        px = uv[idx].astype(np.int64)
        read = view.read_depth()[px[:, 1], px[:, 0]]
        with np.errstate(invalid="ignore"):
            observed[idx[np.abs(read - depth[idx]) < DEPTH_AGREES_M]] = True
    n = grid.shape[0] * grid.shape[1]
    return {
        "seen_by_a_view": float(seen.reshape(-1, n).any(axis=0).mean()),
        "observed_by_a_depth_map": float(observed.reshape(-1, n).any(axis=0).mean()),
    }


def voxel_proxy_floor(
    truth: Truth, footprints: Path, r: float = 1.0, cluster_error: float = 0.3
) -> dict:
    """Median absolute building height error (percent) of perfect 2.5D proxies: the
    true height above ground of every ``r`` column of each true footprint, clustered by
    the voxel path's :func:`~modeling.voxel.proxy.cluster_heights` with ``cluster_error``
    and snapped to the cluster means, scored as ``workbench compare`` scores a run."""
    grid, ids = truth.grid, truth.building_ids
    above = truth.building_surface - truth.dtm
    surface = np.array(truth.dtm, dtype=np.float64)
    X, Y = grid.cell_centers()
    for f in read_footprints(footprints):
        try:
            k = int(f.id)
        except ValueError:
            continue
        cells = ids == k
        if not cells.any():
            continue
        frame, columns = voxelise(f.polygon.convex_hull, 1.0, 0.0, r, 0.0)
        xy = frame.column_centres()[columns]
        row, col = grid.cell_index(xy[:, 0], xy[:, 1], clip=True)
        on = ids[row, col] == k
        if not on.any():
            continue
        h = above[row, col][on]
        labels, centres = cluster_heights(h, cluster_error)
        snapped = np.full(frame.shape[:2], np.nan)
        ij = np.argwhere(columns)[on]
        snapped[ij[:, 0], ij[:, 1]] = centres[labels]
        local = frame.to_local_xy(np.column_stack([X[cells], Y[cells]]))
        i = np.clip(((local[:, 0] - frame.x0) // r).astype(np.int64), 0, frame.shape[0] - 1)
        j = np.clip(((local[:, 1] - frame.y0) // r).astype(np.int64), 0, frame.shape[1] - 1)
        z = snapped[i, j]
        surface[cells] = np.where(np.isfinite(z), truth.dtm[cells] + z, truth.dtm[cells])
    err = metrics.height_error_pct(
        metrics.building_heights(surface, truth.dtm, ids),
        metrics.building_heights(truth.building_surface, truth.dtm, ids),
    )
    return {
        "voxel_m": r,
        "cluster_error": cluster_error,
        "height_error_pct_median": float(np.median(np.abs(list(err.values())))),
    }


def outline_inside_floor(truth: Truth, cells: tuple[int, ...] = (1, 2, 3, 4)) -> dict:
    """{metres: errors} of a perfect model whose outlines lie ``k`` cells inside the
    truth's: a building keeps the cells whose (2k + 1)-cell square it holds whole, and
    the cells it loses stand at the true ground's height; scored over the true building
    cells as a model's heights are (``metrics.height_errors``: ``rmse_m``,
    ``rmse_off_jumps_m``, ...). The grid's border is no outline."""
    from scipy import ndimage

    ids = truth.building_ids
    out = {}
    for k in cells:
        size = (2 * k + 1,) * 2
        low = ndimage.grey_erosion(ids, size=size, mode="nearest")
        high = ndimage.grey_dilation(ids, size=size, mode="nearest")
        kept = (ids > 0) & (low == ids) & (high == ids)
        surface = np.where(kept, truth.building_surface, truth.dtm)
        out[f"{k * truth.grid.gsd:g}"] = metrics.height_errors(
            surface, truth.building_surface, mask=ids > 0
        )
    return out


def height_floor(scene_dir: Path, returns: int = 15, seed: int = 0) -> dict:
    """The floor figures of one sample scene (see the module docstring)."""
    truth = load_scene_truth(scene_dir)
    vertices, triangles, props = read_ply(Path(scene_dir) / "truth" / "mesh.ply")
    grid = truth.grid
    x0, y0, x1, y1 = grid.bounds
    origin = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    local = vertices - origin
    scene = raycasting_scene(local, triangles)
    # a model has no trees: over building cells it is read on buildings and terrain
    bare = raycasting_scene(local, triangles[props["class"] != CLASS_TREE])
    top = float(local[:, 2].max()) + 10.0
    rng = np.random.default_rng(seed)
    half = grid.gsd / 2
    reads = [
        surface_at(scene, grid, origin, top, *rng.uniform(-half, half, (2,) + grid.shape))
        for _ in range(returns)
    ]
    fused = np.median(np.stack(reads), axis=0)
    building = truth.building_ids > 0
    dsm = metrics.height_errors(fused, truth.dsm)
    out = {
        "scene": str(scene_dir),
        "gsd": grid.gsd,
        "returns_per_cell": returns,
        "median_of_returns": {
            "dsm_rmse_m": dsm["rmse_m"],
            "dsm_rmse_off_jumps_m": dsm["rmse_off_jumps_m"],
            "building_rmse_m": metrics.height_errors(fused, truth.building_surface, mask=building)[
                "rmse_m"
            ],
        },
        "walls_displaced": {},
    }
    for d in (0.0, 0.05, 0.1, 0.25):
        angle = rng.uniform(0, 2 * np.pi, grid.shape)
        moved = surface_at(bare, grid, origin, top, d * np.cos(angle), d * np.sin(angle))
        e = metrics.height_errors(moved, truth.building_surface, mask=building)
        out["walls_displaced"][f"{d:g}"] = {"building_rmse_m": e["rmse_m"]}
    out["outline_inside"] = {
        d: {"building_rmse_m": e["rmse_m"], "building_rmse_off_jumps_m": e["rmse_off_jumps_m"]}
        for d, e in outline_inside_floor(truth).items()
    }
    out["cells"] = cells_seen(Path(scene_dir), grid, scene, origin, top)
    footprints = Path(scene_dir) / "truth" / "footprints.geojson"
    if footprints.exists():
        out["voxel_proxies"] = [voxel_proxy_floor(truth, footprints, 1.0, c) for c in (0.3, 0.05)]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--returns", type=int, default=15)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    mesh = args.scene / "truth" / "mesh.ply"
    if not mesh.exists():
        raise SystemExit(f"height_floor: {mesh}: missing (a sample scene's true mesh)")
    f = height_floor(args.scene, args.returns, args.seed)
    m = f["median_of_returns"]
    print(
        f"noise-free fusion, median of {f['returns_per_cell']} returns per "
        f"{f['gsd']:g} m cell: DSM RMSE {m['dsm_rmse_m']:.2f} m "
        f"({m['dsm_rmse_off_jumps_m']:.2f} m off height jumps), "
        f"over true building cells {m['building_rmse_m']:.2f} m"
    )
    walls = ", ".join(
        f"{d} m: {v['building_rmse_m']:.2f} m" for d, v in f["walls_displaced"].items()
    )
    print(f"perfect model with walls displaced by {walls} (over true building cells)")
    inside = ", ".join(
        f"{d} m: {v['building_rmse_off_jumps_m']:.2f} m" for d, v in f["outline_inside"].items()
    )
    print(f"perfect model with outlines inside the true ones by {inside} (off height jumps)")
    c = f["cells"]
    print(
        f"cells whose true surface some view sees {c['seen_by_a_view']:.1%}, "
        f"that some depth map observes within {DEPTH_AGREES_M} m "
        f"{c['observed_by_a_depth_map']:.1%}"
    )
    for v in f.get("voxel_proxies", []):
        print(
            f"perfect {v['voxel_m']:g} m voxel proxies, clustered with c_e "
            f"{v['cluster_error']:g}: building height error, median "
            f"{v['height_error_pct_median']:.1f} %"
        )
    if args.json:
        args.json.write_text(json.dumps(f, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""What the height metrics can reach at all: the scores of noise-free sensors.

The truth DSM of a sample is the true surface read at each cell centre. A fused DSM
is a median over returns spread over the cell, and a model's wall is never exactly
where the truth's is; beside a wall either is a wall's height off. This script reads
the true mesh with vertical rays and scores, with the metrics of ``workbench compare``:

- the median of ``k`` returns at random places in each cell (a perfect, noise-free
  fusion of ``k`` observations per cell), against the truth DSM and over the true
  building cells (as the models' height RMSE is scored);
- the surface read at the cell centre displaced by ``d`` metres in a random direction
  (a perfect model whose walls are off by ``d``), over the true building cells.

Usage: python benchmarks/height_floor.py SCENE [--returns 15] [--seed 0] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from workbench import metrics
from workbench.meshio import read_ply
from workbench.raster import Grid
from workbench.raycast import cast, raycasting_scene
from workbench.truth import load_scene_truth

CLASS_TREE = 3  # the class property of the sample's truth mesh


def surface_at(scene, grid: Grid, origin: np.ndarray, top: float, dx, dy) -> np.ndarray:
    """(H, W) height of the mesh straight below each cell centre moved by (dx, dy) m,
    NaN where nothing is hit. ``scene`` holds the mesh shifted by ``-origin``."""
    X, Y = grid.cell_centers()
    x = (X + dx - origin[0]).ravel()
    y = (Y + dy - origin[1]).ravel()
    origins = np.column_stack([x, y, np.full(x.size, top)])
    hits = cast(scene, origins, np.tile([0.0, 0.0, -1.0], (x.size, 1)))
    return (hits.points[:, 2] + origin[2]).reshape(grid.shape)


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
    if args.json:
        args.json.write_text(json.dumps(f, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

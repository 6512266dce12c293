"""The 50 AHN3 building clouds: LiDAR in, closed LoD2 models out, scored against the points.

For every cloud of ../shared/data/ahn3_buildings: `workbench fusion --points` then
`workbench model superpixel --all-building`, `workbench model parametric --all-building`
and `workbench model blocks --all-building`, in this process, from the same fusion.
Prints per building and in median, per path: RMS and mean distance from the cloud's
points to the model (Open3D distance queries), triangles, watertightness and seconds
(the fusion's share included); failures are counted, not hidden. City3D's figures on
the same clouds (same kind of machine) are printed beside ours.

Usage: python benchmarks/ahn3.py [--data DIR] [--out DIR] [--limit N] [--paths P ...]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np
import open3d as o3d

from fusion.run import run_fusion
from modeling.blocks.options import BlocksOptions
from modeling.blocks.path import run_blocks
from modeling.parametric.options import ParametricOptions
from modeling.parametric.path import run_parametric
from modeling.superpixel.options import SuperpixelOptions
from modeling.superpixel.path import run_superpixel
from workbench.meshes import concatenate_meshes, read_mesh
from workbench.model_run import model_buildings, write_model_run
from workbench.raycast import raycasting_scene, unsigned_distance

CITY3D = {"rms_m": 0.258, "triangles": 113, "seconds": 1.4}
DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "ahn3_buildings"


# How each path models a cloud of one building (no ground to classify against).
PATHS = {
    "superpixel": lambda fusion: run_superpixel(
        fusion, SuperpixelOptions(all_building=True, min_area_m2=5.0)
    ),
    "parametric": lambda fusion: run_parametric(
        fusion, ParametricOptions(all_building=True, min_area_m2=5.0)
    ),
    "blocks": lambda fusion: run_blocks(fusion, BlocksOptions(all_building=True, min_area_m2=5.0)),
}


def model_cloud(cloud: Path, work: Path, paths: list[str]) -> list[dict]:
    """Fuse one cloud, model it with each path, score each model against the points."""
    t0 = time.perf_counter()
    fusion_dir = work / f"{cloud.stem}_fusion"
    run_fusion(fusion_dir, points=cloud, overwrite=True)
    fusion_s = time.perf_counter() - t0
    points = np.asarray(o3d.io.read_point_cloud(str(cloud)).points)
    rows = []
    for path in paths:
        t0 = time.perf_counter()
        model_dir = work / f"{cloud.stem}_{path}"
        write_model_run(PATHS[path](fusion_dir), model_dir, overwrite=True)
        seconds = fusion_s + time.perf_counter() - t0
        buildings = list(model_buildings(model_dir))  # one building's cloud: a few
        meshes = [read_mesh(model_dir / b["mesh"]) for b in buildings]
        row = {"cloud": cloud.name, "path": path, "seconds": seconds, "buildings": len(meshes)}
        if meshes:
            V, T, _ = concatenate_meshes(meshes)
            d = unsigned_distance(raycasting_scene(V, T), points)
            row |= {
                "points": len(points),
                "triangles": int(len(T)),
                "watertight": all(b["watertight"] for b in buildings),
                "roof_types": [b["roof_type"] for b in buildings],
                "rms_m": float(np.sqrt(np.mean(d**2))),
                "mean_m": float(np.mean(d)),
            }
        rows.append(row)
    return rows


def summarise(rows: list[dict], clouds: int, failed: int) -> dict:
    """One path's medians over the clouds it modelled."""
    done = [r for r in rows if r.get("buildings")]
    return {
        "clouds": clouds,
        "modelled": len(done),
        "empty": len(rows) - len(done),
        "failed": failed,
        "watertight": sum(r["watertight"] for r in done),
        "rms_m_median": statistics.median(r["rms_m"] for r in done) if done else None,
        "triangles_median": statistics.median(r["triangles"] for r in done) if done else None,
        "seconds_median": statistics.median(r["seconds"] for r in rows) if rows else None,
        "seconds_max": max(r["seconds"] for r in rows) if rows else None,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, default=Path("bench_out"))
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--paths", nargs="+", choices=list(PATHS), default=list(PATHS))
    args = ap.parse_args()
    if not args.data.is_dir():
        print(f"ahn3: {args.data} not found; skipped")
        return 0
    clouds = sorted(args.data.glob("*.ply"), key=lambda p: int(p.stem) if p.stem.isdigit() else 0)
    clouds = clouds[: args.limit] if args.limit else clouds
    rows, failures = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for cloud in clouds:
            try:
                new = model_cloud(cloud, Path(tmp), args.paths)
            except Exception as exc:  # noqa: BLE001 - a benchmark counts failures
                failures.append({"cloud": cloud.name, "error": f"{type(exc).__name__}: {exc}"})
                traceback.print_exc()
                continue
            rows += new
            for r in new:
                if r.get("buildings"):
                    print(
                        f"  {cloud.name:>7} {r['path']:>10}: {r['points']:>5} points, RMS "
                        f"{r['rms_m']:.3f} m, {r['triangles']:>4} triangles, watertight "
                        f"{r['watertight']}, {r['seconds']:.2f} s"
                    )
                else:
                    print(f"  {cloud.name:>7} {r['path']:>10}: no building modelled")
    summary = {p: summarise([r for r in rows if r["path"] == p], len(clouds), len(failures))
               for p in args.paths}  # fmt: skip
    summary["city3d"] = CITY3D
    print(f"\nAHN3 building clouds ({len(clouds)}; {len(failures)} failed to fuse or model):")
    for p in args.paths:
        s = summary[p]
        line = f"  {p}: {s['modelled']} modelled ({s['empty']} empty), {s['watertight']} watertight"
        if s["modelled"]:
            line += (
                f"; median RMS {s['rms_m_median']:.3f} m, median {s['triangles_median']:.0f} "
                f"triangles, median {s['seconds_median']:.2f} s per building, max "
                f"{s['seconds_max']:.2f} s"
            )
        print(line)
    print(
        f"  City3D: median RMS {CITY3D['rms_m']} m, {CITY3D['triangles']} triangles, "
        f"{CITY3D['seconds']} s"
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ahn3.json").write_text(
        json.dumps({"summary": summary, "rows": rows, "failures": failures}, indent=1) + "\n"
    )
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

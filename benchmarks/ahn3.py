"""The 50 AHN3 building clouds: LiDAR in, closed LoD2 models out, scored against the points.

For every cloud of ../shared/data/ahn3_buildings: `workbench fusion --points` then
`workbench model superpixel --all-building`, both in this process. Prints per building
and in median: RMS and mean distance from the cloud's points to the model (Open3D distance
queries), triangles, watertightness and seconds; failures are counted, not hidden.
City3D's figures on the same clouds (same kind of machine) are printed beside ours.

Usage: python benchmarks/ahn3.py [--data DIR] [--out DIR] [--limit N]
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
from modeling.superpixel.options import SuperpixelOptions
from modeling.superpixel.path import run_superpixel
from workbench.meshes import concatenate_meshes, read_mesh
from workbench.model_run import write_model_run
from workbench.raycast import raycasting_scene, unsigned_distance

CITY3D = {"rms_m": 0.258, "triangles": 113, "seconds": 1.4}
DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "ahn3_buildings"


def model_cloud(cloud: Path, work: Path) -> dict:
    """Fuse and model one cloud; score the model against the cloud's points."""
    t0 = time.perf_counter()
    fusion_dir, model_dir = work / f"{cloud.stem}_fusion", work / f"{cloud.stem}_model"
    run_fusion(fusion_dir, points=cloud, overwrite=True)
    options = SuperpixelOptions(all_building=True, min_area_m2=5.0)
    record = write_model_run(run_superpixel(fusion_dir, options), model_dir, overwrite=True)
    seconds = time.perf_counter() - t0
    points = np.asarray(o3d.io.read_point_cloud(str(cloud)).points)
    meshes = [read_mesh(model_dir / b["mesh"]) for b in record["buildings"]]
    if not meshes:
        return {"cloud": cloud.name, "seconds": seconds, "buildings": 0}
    V, T, _ = concatenate_meshes(meshes)
    d = unsigned_distance(raycasting_scene(V, T), points)
    return {
        "cloud": cloud.name,
        "points": len(points),
        "buildings": len(meshes),
        "triangles": int(len(T)),
        "watertight": all(b["watertight"] for b in record["buildings"]),
        "rms_m": float(np.sqrt(np.mean(d**2))),
        "mean_m": float(np.mean(d)),
        "seconds": seconds,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, default=Path("bench_out"))
    ap.add_argument("--limit", type=int, default=None)
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
                rows.append(model_cloud(cloud, Path(tmp)))
            except Exception as exc:  # noqa: BLE001 - a benchmark counts failures
                failures.append({"cloud": cloud.name, "error": f"{type(exc).__name__}: {exc}"})
                traceback.print_exc()
            r = rows[-1] if rows and rows[-1]["cloud"] == cloud.name else None
            if r and r.get("buildings"):
                print(
                    f"  {cloud.name:>7}: {r['points']:>5} points, RMS {r['rms_m']:.3f} m, "
                    f"{r['triangles']:>4} triangles, watertight {r['watertight']}, "
                    f"{r['seconds']:.2f} s"
                )
            elif r:
                print(f"  {cloud.name:>7}: no building modelled")
    done = [r for r in rows if r.get("buildings")]
    summary = {
        "clouds": len(clouds),
        "modelled": len(done),
        "empty": len(rows) - len(done),
        "failed": len(failures),
        "watertight": sum(r["watertight"] for r in done),
        "rms_m_median": statistics.median(r["rms_m"] for r in done) if done else None,
        "triangles_median": statistics.median(r["triangles"] for r in done) if done else None,
        "seconds_median": statistics.median(r["seconds"] for r in rows) if rows else None,
        "seconds_max": max(r["seconds"] for r in rows) if rows else None,
        "city3d": CITY3D,
    }
    print(
        f"\nAHN3 building clouds: {summary['modelled']} of {summary['clouds']} modelled "
        f"({summary['failed']} failed, {summary['empty']} empty), {summary['watertight']} "
        f"watertight"
    )
    if done:
        print(
            f"  median RMS {summary['rms_m_median']:.3f} m (City3D {CITY3D['rms_m']}), "
            f"median {summary['triangles_median']:.0f} triangles (City3D "
            f"{CITY3D['triangles']}), median {summary['seconds_median']:.2f} s per building, "
            f"max {summary['seconds_max']:.2f} s (City3D median {CITY3D['seconds']} s)"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ahn3.json").write_text(
        json.dumps({"summary": summary, "rows": rows, "failures": failures}, indent=1) + "\n"
    )
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

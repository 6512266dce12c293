"""A whole preset end to end, as a user runs it: ``workbench sample``, ``fusion``, the
modeling paths that run from a scene or a fusion (super-pixel, voxel, parametric, blocks),
``workbench mesh`` and ``fusion --mesh`` with the LOD path on that mesh's fusion (as its
paper has it), the scene scanned as LiDAR tiles and ``fusion --points`` on them, and
``compare``, each a command of its own; wall time, throughput and the
peak memory of every process (the command's, and each Dask worker's). The super-pixel and
LOD paths run again with ``--workers 1``: what the workers buy.

``make bench BENCH_ARGS="--preset city"`` runs it on the 1 km² city (about two hours on
2 cores); ``--preset small`` gives the same table on the everyday sample, to set beside
it: peak memory must not grow with the area.

Usage: python benchmarks/city.py [--preset city] [--seed 0] [--out bench_out/city]
       [--workers 2] [--reuse] [--reuse-runs]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent / "workbench"
# the child's own high-water mark, printed by the shell after the command (Linux)
TIME = ["/usr/bin/time", "-f", "maxrss_kb %M"] if Path("/usr/bin/time").exists() else []


def run(*args, log: Path, kept: float | None = None) -> tuple[float, float | None]:
    """Run ``workbench *args``; returns wall seconds and the command's peak RSS in MiB.

    With ``kept`` (the seconds an earlier run's record gives), an earlier run whose log
    is there is taken as it is."""
    wall_file = log.with_suffix(".wall")
    if kept is not None and log.exists() and "maxrss_kb" in log.read_text():
        if wall_file.exists():  # the earlier run's own wall time
            kept = float(wall_file.read_text())
        return kept, _peak(log.read_text())
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.run([*TIME, str(BIN), *map(str, args)], stdout=f,
                              stderr=subprocess.STDOUT)  # fmt: skip
    wall = time.perf_counter() - t0
    text = log.read_text()
    if proc.returncode != 0:
        raise SystemExit(f"failed ({proc.returncode}): workbench {' '.join(map(str, args))}\n"
                         f"{text[-2000:]}")  # fmt: skip
    wall_file.write_text(f"{wall:.3f}\n")
    return wall, _peak(text)


def _peak(text: str) -> float | None:
    peak = [ln for ln in text.splitlines() if ln.startswith("maxrss_kb ")]
    return float(peak[-1].split()[1]) / 1024 if peak else None


def _mesh_worker_peaks(text: str) -> list[float] | None:
    """The peak memory of `workbench mesh`'s workers (MiB), from what it printed."""
    for line in text.splitlines():
        if "Dask workers; their peak memory" in line:
            return [float(p) for p in line.split("peak memory")[1].strip(" MiB").split(",")]
    return None


def _recorded_s(record: Path, key: str | None = None) -> float | None:
    """The seconds a finished run's record gives: its ``key``, else the sum of its
    stages (None if there is no such run)."""
    if not record.exists():
        return None
    rec = json.loads(record.read_text())
    if key is not None and rec.get(key) is not None:
        return rec[key]
    return sum(s["wall_s"] for s in rec["stages"].values())


def city_run(
    preset: str,
    seed: int,
    out: Path,
    workers: int | None,
    reuse: bool,
    reuse_runs: bool = False,
    block_m: float | None = None,
) -> dict:
    """Every stage on one preset and seed; the figures of each. ``reuse`` keeps an
    existing sample scene; ``reuse_runs`` also the runs whose logs are there; with
    ``block_m``, the fusion and the paths of ``BLOCK_PATHS`` are run again in blocks of
    that side (``--block``)."""
    out.mkdir(parents=True, exist_ok=True)
    scene, fusion, report = out / "scene", out / "fusion", out / "report"
    w = ["--workers", str(workers)] if workers else []
    res: dict = {"preset": preset, "seed": seed, "workers": workers}
    if not (reuse and (scene / "scene.json").exists()):
        wall, peak = run("sample", scene, "--preset", preset, "--seed", seed, "--overwrite",
                         log=out / "sample.log")  # fmt: skip
        res["sample"] = {"wall_s": wall, "peak_mb": peak}
    meta_path = scene / "sample.json"
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    res["buildings_in_truth"] = meta.get("counts", {}).get("buildings")
    res["views"] = meta.get("counts", {}).get("views")

    kept = _recorded_s(fusion / "fusion.json", "stages_total_s") if reuse_runs else None
    wall, peak = run("fusion", scene, "-o", fusion, "--truth", scene, *w, "--overwrite",
                     log=out / "fusion.log", kept=kept)  # fmt: skip
    rec = json.loads((fusion / "fusion.json").read_text())
    res["fusion"] = {
        "wall_s": wall, "peak_mb": peak, "own_peak_mb": rec.get("peak_memory_mb"),
        "worker_peak_mb": rec.get("worker_peak_memory_mb"),
        "stages": {k: v["wall_s"] for k, v in rec["stages"].items()},
        "observations": rec["observations"], "observations_per_s": rec["observations_per_s"],
        "cells": rec["grid"]["width"] * rec["grid"]["height"], "tiles": rec.get("tiles"),
        "engine": rec.get("engine"), "workers": rec.get("workers"),
        "quality": rec.get("quality", {}),
    }  # fmt: skip
    if block_m is not None:  # the same fusion in blocks: the command's memory follows the block
        blocked = out / "fusion_blocks"
        kept = _recorded_s(blocked / "fusion.json", "stages_total_s") if reuse_runs else None
        wall, peak = run("fusion", scene, "-o", blocked, "--truth", scene, "--block", block_m,
                         *w, "--overwrite", log=out / "fusion_blocks.log", kept=kept)  # fmt: skip
        rec = json.loads((blocked / "fusion.json").read_text())
        res["fusion_blocks"] = {
            "wall_s": wall, "peak_mb": peak, "own_peak_mb": rec.get("peak_memory_mb"),
            "worker_peak_mb": rec.get("worker_peak_memory_mb"), **rec["blocks"],
            "quality": rec.get("quality", {}),
        }  # fmt: skip
    paths = {"superpixel": ["superpixel", fusion],
             "voxel": ["voxel", scene, "--fusion", fusion, *w],
             "parametric": ["parametric", fusion, *w],
             "blocks": ["blocks", fusion, *w]}  # fmt: skip
    for name, args in paths.items():
        folder = out / name
        kept = _recorded_s(folder / "model.json") if reuse_runs else None
        wall, peak = run("model", *args, "-o", folder, "--overwrite", log=out / f"{name}.log",
                         kept=kept)  # fmt: skip
        res[name] = model_figures(folder, wall, peak)
    if block_m is not None:  # the paths that model in blocks: their memory follows the block
        for name in BLOCK_PATHS:
            folder = out / f"{name}_blocks"
            kept = _recorded_s(folder / "model.json") if reuse_runs else None
            wall, peak = run("model", *paths[name], "--block", block_m, "-o", folder,
                             "--overwrite", log=out / f"{name}_blocks.log", kept=kept)  # fmt: skip
            res[f"{name}_blocks"] = model_figures(folder, wall, peak)
    res.update(mesh_chain(scene, out, reuse_runs, block_m))
    res.update(lidar_chain(scene, out, reuse_runs))
    # two paths again in the command's process alone: what the workers buy
    labels = ("--labels", scene / "training" / "labels.tif")
    for name, args in (("superpixel", paths["superpixel"]),
                       ("lod", ["lod", out / "fusion_mesh", *labels])):  # fmt: skip
        folder = out / f"{name}_one"
        kept = _recorded_s(folder / "model.json") if reuse_runs else None
        wall, peak = run("model", *args, "--workers", "1", "-o", folder, "--overwrite",
                         log=out / f"{name}_one.log", kept=kept)  # fmt: skip
        res[f"{name}_one"] = model_figures(folder, wall, peak)
    runs = [fusion, *(out / name for name in paths), out / "lod"]
    kept = 0.0 if reuse_runs and (report / "metrics.json").exists() else None
    wall, peak = run("compare", *runs, "--truth", scene, "-o", report, "--overwrite",
                     log=out / "compare.log", kept=kept)  # fmt: skip
    res["compare"] = {"wall_s": wall, "peak_mb": peak}
    res["total_s"] = sum(v["wall_s"] for v in res.values() if isinstance(v, dict) and
                         "wall_s" in v)  # fmt: skip
    return res


# the modeling paths that model a grid in blocks (``--block``)
BLOCK_PATHS = ("superpixel", "parametric", "blocks")


def mesh_chain(scene: Path, out: Path, reuse_runs: bool = False,
               block_m: float | None = None) -> dict:  # fmt: skip
    """``workbench mesh`` (tiled as it decides), ``fusion --mesh`` on the scene's grid and
    the LOD path on that fusion with the scene's training strokes (with ``block_m``, again
    in blocks of that side): their figures."""
    mesh, fusion = out / "mesh" / "mesh.ply", out / "fusion_mesh"
    doc = json.loads((scene / "scene.json").read_text())
    res = {}
    kept = 0.0 if reuse_runs and mesh.exists() else None
    wall, peak = run("mesh", scene, "-o", mesh, "--overwrite", log=out / "mesh.log", kept=kept)
    workers = _mesh_worker_peaks((out / "mesh.log").read_text())
    res["mesh"] = {"wall_s": wall, "peak_mb": peak, "worker_peak_mb": workers}
    kept = _recorded_s(fusion / "fusion.json", "stages_total_s") if reuse_runs else None
    wall, peak = run("fusion", "--mesh", mesh, "-o", fusion, "--gsd", doc["gsd"], "--bounds",
                     *doc["bounds"], "--overwrite", log=out / "fusion_mesh.log",
                     kept=kept)  # fmt: skip
    res["fusion_mesh"] = {"wall_s": wall, "peak_mb": peak}
    folder = out / "lod"
    kept = _recorded_s(folder / "model.json") if reuse_runs else None
    labels = ("--labels", scene / "training" / "labels.tif")
    wall, peak = run("model", "lod", fusion, *labels, "-o", folder, "--overwrite",
                     log=out / "lod.log", kept=kept)  # fmt: skip
    res["lod"] = model_figures(folder, wall, peak)
    if block_m is not None:  # the chain in blocks: the mesh's fusion, then the LOD path
        blocks = out / "fusion_mesh_blocks"
        kept = _recorded_s(blocks / "fusion.json", "stages_total_s") if reuse_runs else None
        wall, peak = run("fusion", "--mesh", mesh, "-o", blocks, "--gsd", doc["gsd"],
                         "--bounds", *doc["bounds"], "--block", block_m, "--overwrite",
                         log=out / "fusion_mesh_blocks.log", kept=kept)  # fmt: skip
        res["fusion_mesh_blocks"] = {"wall_s": wall, "peak_mb": peak}
        folder = out / "lod_blocks"
        kept = _recorded_s(folder / "model.json") if reuse_runs else None
        wall, peak = run("model", "lod", blocks, *labels, "--block", block_m, "-o", folder,
                         "--overwrite", log=out / "lod_blocks.log", kept=kept)  # fmt: skip
        res["lod_blocks"] = model_figures(folder, wall, peak)
    return res


def lidar_chain(scene: Path, out: Path, reuse_runs: bool = False) -> dict:
    """The scene scanned as airborne LiDAR tiles of 250 m (:mod:`data_samples.lidar`),
    then ``fusion --points`` on the tiles, as it decides (whole, or blocks as tasks of the
    workers), and again with ``--workers 1``: their figures."""
    tiles, res = out / "lidar", {}
    if not (reuse_runs and (tiles / "lidar.json").exists()):
        subprocess.run([sys.executable, "-m", "data_samples.lidar", str(scene), str(tiles)],
                       check=True, capture_output=True)  # fmt: skip
    n_returns = json.loads((tiles / "lidar.json").read_text())["points"]
    for name, extra in (("fusion_points", ()), ("fusion_points_one", ("--workers", "1"))):
        fusion = out / name
        kept = _recorded_s(fusion / "fusion.json", "stages_total_s") if reuse_runs else None
        wall, peak = run("fusion", "--points", tiles, "-o", fusion, "--truth", scene, *extra,
                         "--overwrite", log=out / f"{name}.log", kept=kept)  # fmt: skip
        rec = json.loads((fusion / "fusion.json").read_text())
        q = rec.get("quality", {})
        res[name] = {
            "wall_s": wall, "peak_mb": peak, "own_peak_mb": rec.get("peak_memory_mb"),
            "worker_peak_mb": rec.get("worker_peak_memory_mb"), "returns": n_returns,
            "cells": rec["grid"]["width"] * rec["grid"]["height"], "blocks": rec.get("blocks"),
            "stages": {k: v["wall_s"] for k, v in rec["stages"].items()},
            "dtm_rmse_m": q.get("dtm", {}).get("rmse_m"),
            "dsm_rmse_off_jumps_m": q.get("dsm", {}).get("rmse_off_jumps_m"),
            "classes": q.get("classification", {}).get("overall_accuracy"),
        }  # fmt: skip
    return res


def model_figures(folder: Path, wall: float, peak: float | None) -> dict:
    """A modeling run's figures: the command's wall time and peak, and from its record
    the buildings, seconds per building, stages and peaks of its own process and workers."""
    rec = json.loads((folder / "model.json").read_text())
    n = rec["counts"]["buildings"]
    return {
        "wall_s": wall, "peak_mb": peak, "buildings": n, "seconds_per_building": wall / max(n, 1),
        "stages": {k: v["wall_s"] for k, v in rec["stages"].items()},
        "own_peak_mb": rec.get("peak_memory_mb"),
        "worker_peak_mb": rec.get("worker_peak_memory_mb"),
    }  # fmt: skip


def print_city(r: dict) -> None:
    """The table of one preset's run."""
    print(f"\n{r['preset']} seed {r['seed']} end to end ({r.get('views')} views, "
          f"{r.get('buildings_in_truth')} buildings in the truth), one run each:")  # fmt: skip

    def peaks(s):
        """The largest process's peak (the command or a worker: `time` sees them all),
        the command's own where its record gives it, each worker's."""
        out = f"peak {s['peak_mb']:.0f} MiB" if s.get("peak_mb") else ""
        if s.get("own_peak_mb"):
            out += f" (command {s['own_peak_mb']:.0f} MiB"
            wp = s.get("worker_peak_mb")
            out += f", workers {', '.join(f'{p:.0f}' for p in wp)} MiB)" if wp else ")"
        elif s.get("worker_peak_mb"):
            out += f" (workers {', '.join(f'{p:.0f}' for p in s['worker_peak_mb'])} MiB)"
        return out

    if "sample" in r:
        print(f"  sample      {r['sample']['wall_s']:8.1f} s  {peaks(r['sample'])}")
    f = r["fusion"]
    print(f"  fusion      {f['wall_s']:8.1f} s  {peaks(f)}; {f['engine']} x {f['workers']}, "
          f"{f['tiles']} tiles of {f['cells'] / 1e6:.2f} M cells; {f['observations'] / 1e6:.1f} M "
          f"observations, {f['observations_per_s'] / 1e6:.2f} M/s")  # fmt: skip
    print("              " + ", ".join(f"{k} {v:.1f}" for k, v in f["stages"].items()))
    if "fusion_blocks" in r:
        b = r["fusion_blocks"]
        print(f"  fusion in {b['count']} blocks of {b['side_m']:g} m (+ {b['margin_m']:g} m "
              f"margins: at most {b['largest_block_cells'] / 1e6:.2f} M cells a block, "
              f"{b['cells_fused_per_cell']:.2f} cells fused per cell)")  # fmt: skip
        print(f"              {b['wall_s']:8.1f} s  {peaks(b)}")
        print_fusion_quality(b.get("quality", {}), "              ")
    m = r["superpixel"]
    print(f"  superpixel  {m['wall_s']:8.1f} s  {peaks(m)}; {m['buildings']} buildings, "
          f"{m['wall_s'] / (f['cells'] / 1e6):.1f} s per ortho megapixel")  # fmt: skip
    names = ("voxel", "parametric", "blocks", *(f"{n}_blocks" for n in BLOCK_PATHS), "mesh",
             "fusion_mesh", "lod", "fusion_mesh_blocks", "lod_blocks", "superpixel_one",
             "lod_one")  # fmt: skip
    for name in names:
        if name not in r:  # a record from before the path was benched
            continue
        m = r[name]
        label = f"{name.removesuffix('_blocks')} --block" if name.endswith("_blocks") else name
        if name.endswith("_one"):  # against the same run on the workers
            base = name.removesuffix("_one")
            label = f"{base} --workers 1 (x {m['wall_s'] / r[base]['wall_s']:.2f})"
        if "buildings" not in m:  # the mesh and its fusion
            print(f"  {label:<11} {m['wall_s']:8.1f} s  {peaks(m)}")
            continue
        print(f"  {label:<11} {m['wall_s']:8.1f} s  {peaks(m)}; {m['buildings']} buildings, "
              f"{m['seconds_per_building']:.2f} s per building")  # fmt: skip
        print("              " + ", ".join(f"{k} {v:.1f}" for k, v in m["stages"].items()))
    for name in ("fusion_points", "fusion_points_one"):
        if name not in r:  # a record from before it was benched
            continue
        p = r[name]
        b, how = p.get("blocks"), "whole"
        if b:
            how = (f"{b['count']} blocks of {b['side_m']:g} m (+ {b['margin_m']:g} m margins: "
                   f"at most {b['largest_block_returns'] / 1e6:.2f} M returns a block, "
                   f"{b['returns_read_per_return']:.2f} returns read per return")  # fmt: skip
            if "triangulated_per_cell" in b:  # a record from before lacks it
                how += f", {b['triangulated_per_cell']:.2f} triangulated per cell"
            how += ")"
        ratio = p["wall_s"] / r["fusion_points"]["wall_s"]
        label = name if name == "fusion_points" else f"fusion_points --workers 1 (x {ratio:.2f})"
        print(f"  {label:<11} {p['wall_s']:8.1f} s  {peaks(p)}; {p['returns'] / 1e6:.2f} M "
              f"returns, {p['returns'] / p['wall_s'] / 1e6:.2f} M/s, {how}")  # fmt: skip
        print("              " + ", ".join(f"{k} {v:.1f}" for k, v in p["stages"].items()))
        if p.get("classes") is not None:
            dsm, dtm = p["dsm_rmse_off_jumps_m"], p["dtm_rmse_m"]
            print(f"              classes overall {p['classes']:.3f}, DSM RMSE off jumps "
                  f"{dsm:.2f} m, DTM RMSE {dtm:.3f} m")  # fmt: skip
    print(f"  compare     {r['compare']['wall_s']:8.1f} s  {peaks(r['compare'])}")
    print(f"  total       {r['total_s']:8.1f} s")
    print_fusion_quality(f.get("quality", {}), "  fusion ")


def print_fusion_quality(q: dict, lead: str) -> None:
    """A fusion's classes and DSM against the truth, on one line after ``lead``."""
    if q.get("classification"):
        off = q["dsm"].get("rmse_off_jumps_m", float("nan"))
        print(f"{lead}classes overall {q['classification']['overall_accuracy']:.3f}, "
              f"DSM RMSE off jumps {off:.2f} m")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="city")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("bench_out") / "city")
    ap.add_argument("--workers", type=int, help="default: every core")
    ap.add_argument("--reuse", action="store_true", help="keep an existing sample scene")
    ap.add_argument(
        "--reuse-runs", action="store_true",
        help="also keep the runs whose logs are there (their time is then their record's, "
        "without the interpreter's start)",
    )  # fmt: skip
    args = ap.parse_args()
    res = city_run(args.preset, args.seed, args.out, args.workers, args.reuse, args.reuse_runs)
    (args.out / "city.json").write_text(json.dumps(res, indent=1) + "\n")
    print_city(res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The truth of a synthetic scene written as a model run: a reference row in a report, and
the check that the metrics score the truth against itself as perfect."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from workbench.meshio import read_ply, write_ply


def truth_model_run(
    scene: Path, out: Path, *, shift=(0.0, 0.0, 0.0), drop: tuple[int, ...] = ()
) -> Path:
    """Write the true buildings of ``scene`` as a model run, each moved by ``shift``
    (metres) and without the buildings in ``drop``."""
    vertices, triangles, props = read_ply(scene / "truth" / "mesh.ply")
    records = json.loads((scene / "truth" / "buildings.json").read_text())["buildings"]
    (out / "buildings").mkdir(parents=True)
    buildings = []
    for rec in records:
        if rec["id"] in drop:
            continue
        tri = triangles[props["building_id"] == rec["id"]]
        used, local = np.unique(tri, return_inverse=True)
        write_ply(
            out / "buildings" / f"{rec['id']}.ply",
            vertices[used] + np.asarray(shift),
            local.reshape(-1, 3),
        )
        buildings.append({"id": str(rec["id"]), "roof_type": rec["roof_type"]})
    record = {
        "method": "truth",
        "buildings": buildings,
        "stages": {"copy": {"wall_s": 0.5, "peak_memory_mb": 100.0}},
    }
    (out / "model.json").write_text(json.dumps(record))
    return out


def truth_fusion_run(scene: Path, out: Path) -> Path:
    """Write the truth rasters of ``scene`` as a fusion run (one-hot class probabilities):
    what a perfect fusion would give, to test the modeling paths apart from the fusion's
    errors."""
    from workbench.raster import read_raster, write_raster

    out.mkdir(parents=True)
    rasters = {}
    for name in ("ortho", "dsm", "dtm", "class"):
        data, grid, crs = read_raster(scene / "truth" / f"{name}.tif")
        rasters[name] = data
        nodata = 0 if name == "class" else None
        write_raster(
            out / f"{name}.tif", data if len(data) > 1 else data[0], grid, crs, nodata=nodata
        )
    cls = rasters["class"][0]
    prob = np.stack([(cls == k).astype(np.float32) for k in (1, 2, 3, 4)])
    write_raster(out / "class_prob.tif", prob, grid, crs)
    write_raster(out / "ndsm.tif", rasters["dsm"][0] - rasters["dtm"][0], grid, crs)
    record = {"method": "truth", "stages": {"copy": {"wall_s": 2.0, "peak_memory_mb": 100.0}}}
    (out / "fusion.json").write_text(json.dumps(record))
    return out

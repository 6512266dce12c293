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

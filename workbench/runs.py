"""Run folders: what `workbench fusion` and every `workbench model ...` leave behind.

A fusion run holds ``fusion.json`` and its rasters. A model run holds ``model.json``
(written by :func:`workbench.model_run.write_model_run`; the schema is in
``docs/formats.md``) and one mesh per building in world coordinates (``mesh`` defaults to
``buildings/<id>.ply``, then ``.obj``), and optionally ``class.tif`` and ``dtm.tif`` on any
grid. Only ``buildings``, each with an ``id``, is required, so that the output of another
tool can be compared; whatever else is there gets scored.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .meshes import read_mesh


@dataclass
class ModelBuilding:
    """One building of a model run: its record in model.json and its mesh
    (vertices (V, 3) float64 world metres, triangles (T, 3) int64)."""

    id: str
    record: dict
    vertices: np.ndarray
    triangles: np.ndarray


@dataclass
class Run:
    """A run folder, read.

    Attributes
    ----------
    name : str
        Its name in the report.
    folder : Path
    kind : str
        ``"fusion"`` or ``"model"``.
    record : dict
        fusion.json or model.json.
    buildings : list of ModelBuilding
        Model runs only.
    """

    name: str
    folder: Path
    kind: str
    record: dict
    buildings: list[ModelBuilding] = field(default_factory=list)

    @property
    def method(self) -> str:
        return self.record.get("method", self.kind)

    def raster(self, name: str) -> Path | None:
        """``folder/<name>.tif`` if the run has it."""
        path = self.folder / f"{name}.tif"
        return path if path.exists() else None


def load_run(folder: str | Path, name: str | None = None) -> Run:
    """Read a fusion or model run folder, checking what the metrics rely on.

    Raises
    ------
    InputError
        Naming the file and the field: not a run folder, unreadable JSON, a building
        without a mesh, an unreadable mesh.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, None, "no such run folder")
    name = name or folder.name
    found = [
        (kind, folder / file)
        for kind, file in (("model", "model.json"), ("fusion", "fusion.json"))
        if (folder / file).exists()
    ]
    if not found:
        raise InputError(folder, None, "not a run folder: no model.json or fusion.json")
    kind, path = found[0]
    try:
        record = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"not valid JSON ({exc})") from None
    if not isinstance(record, dict):
        raise InputError(path, None, "expected a JSON object")
    stages = record.get("stages", {})
    if not isinstance(stages, dict) or not all(isinstance(s, dict) for s in stages.values()):
        raise InputError(path, "stages", "expected {stage: {wall_s, peak_memory_mb}}")
    run = Run(name, folder, kind, record)
    if kind == "model":
        run.buildings = _model_buildings(path, record)
    elif not (folder / "dsm.tif").exists():
        raise InputError(folder / "dsm.tif", None, "a fusion run without its DSM")
    return run


def _model_buildings(path: Path, record: dict) -> list[ModelBuilding]:
    items = record.get("buildings")
    if not isinstance(items, list):
        raise InputError(path, "buildings", "expected a list of buildings")
    out, seen = [], set()
    for i, b in enumerate(items):
        where = f"buildings[{i}]"
        if not isinstance(b, dict) or "id" not in b:
            raise InputError(path, where, "expected an object with an id")
        bid = str(b["id"])
        if bid in seen:
            raise InputError(path, f"{where}.id", f"duplicate building id {bid!r}")
        seen.add(bid)
        if "mesh" in b:
            mesh = path.parent / str(b["mesh"])
        else:
            mesh = path.parent / "buildings" / f"{bid}.ply"
            if not mesh.exists():
                mesh = mesh.with_suffix(".obj")
        if not mesh.exists():
            raise InputError(path, f"{where}.mesh", f"no mesh file ({mesh.name})")
        vertices, triangles = read_mesh(mesh)
        out.append(ModelBuilding(bid, b, vertices, triangles))
    return out

"""The run contract every modeling path honours: a :class:`ModelRun` in memory, one
run folder on disk, written by :func:`write_model_run` whatever the path.

A run folder holds::

    model.json              one schema for every path (SCHEMA), read by `workbench compare`
    model.city.json         the buildings as CityJSON 2.0 (LOD0, LOD1.2 and the path's
                            mesh with semantic surfaces; :mod:`workbench.cityjson`)
    buildings/<id>.ply      each building, world metres, vertex colours (the scored mesh)
    buildings/<id>.obj|.mtl the same, with its texture atlas <id>.png where the path makes one
    scene.ply, scene.obj    every building and the ground in one mesh (+ scene.mtl)
    ground.ply, ground.obj  the ground the buildings stand on (+ ground.png if textured; a
                            ground textured in tiles has a material and a ground/K.png
                            per tile)
    dtm.tif                 that ground as a north-up float32 GeoTIFF, NaN nodata
    <name>.tif              the path's own rasters (class.tif, superpixels.tif, ...)
    preview.png             what the path wants a person to look at

Every building of ``model.json`` has the keys of ``BUILDING_KEYS``; a path adds its own
after them.
"""

from __future__ import annotations

import json
import logging
import pickle
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from shapely.geometry import mapping

from .atomic import atomic_output_dir
from .cityjson import SPOOL_BYTES, CityModelWriter, city_origin, rms_to_heights
from .imageio import write_rgb
from .meshes import is_watertight
from .meshio import write_mtl, write_obj, write_obj_pieces, write_ply, write_ply_pieces
from .options import options_record
from .raster import Grid, write_raster
from .records import StageTimer, peak_memory_mb, provenance

log = logging.getLogger(__name__)

SCHEMA = "city-workbench/model-run/1"
BUILDING_KEYS = (
    "id", "lod", "mesh", "footprint", "roof_type", "planes", "base_z", "eave_z", "ridge_z",
    "faces", "watertight",
)  # fmt: skip
_GREY = (170, 170, 170)


@dataclass
class Texture:
    """A texture atlas and where each triangle corner falls in it.

    image : (h, w, 3) uint8; uvs : (T, 3, 2) float, u right and v up, 0-1."""

    image: np.ndarray
    uvs: np.ndarray


@dataclass
class Surface:
    """A mesh in world metres: vertices (V, 3) float64, triangles (T, 3) int64 counter-
    clockwise seen from outside, optional vertex colours (V, 3) uint8 and texture."""

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_colors: np.ndarray | None = None
    texture: Texture | None = None


@dataclass
class SurfacePieces:
    """An untextured surface too large to hold, kept on disk in pieces (a city's ground,
    block by block) and written piece by piece: what its pieces put together would be.

    Attributes
    ----------
    folder : Path
        Where the pieces are (one ``.npz`` each).
    files : list of Path
    n_vertices, n_triangles : int
        Their totals.
    colour_medians : list of (3,) uint8
        Each piece's median vertex colour (its material's colour is their median).
    """

    folder: Path
    files: list = field(default_factory=list)
    n_vertices: int = 0
    n_triangles: int = 0
    colour_medians: list = field(default_factory=list)
    texture = None  # never textured

    def add(self, s: Surface) -> None:
        """Keep ``s`` (with vertex colours) as the next piece."""
        path = Path(self.folder) / f"piece_{len(self.files)}.npz"
        np.savez(path, vertices=s.vertices, triangles=s.triangles, colours=s.vertex_colors)
        self.files.append(path)
        self.n_vertices += len(s.vertices)
        self.n_triangles += len(s.triangles)
        self.colour_medians.append(np.median(s.vertex_colors, axis=0))

    def pieces(self):
        """Yields each piece as (vertices, triangles, vertex colours), read from disk."""
        for path in self.files:
            with np.load(path) as z:
                yield z["vertices"], z["triangles"], z["colours"]


class TexturedPieces:
    """A textured surface in pieces, each a :class:`Surface` with its own texture image (a
    city's ground, tile by tile): held, or on disk with a folder (one pickle a piece), and
    written piece by piece, a material and an image each. Iterating gives the pieces.

    Parameters
    ----------
    folder : path, optional
        Where the pieces wait (default: held in memory).
    """

    def __init__(self, folder: str | Path | None = None):
        self.folder = Path(folder) if folder is not None else None
        self._held: list[Surface] = []
        self.count = 0

    def add(self, s: Surface) -> None:
        """Keep ``s`` (textured, with vertex colours) as the next piece."""
        if self.folder is None:
            self._held.append(s)
        else:
            with open(self.folder / f"piece_{self.count}.pkl", "wb") as f:
                pickle.dump(s, f, protocol=5)
        self.count += 1

    def __len__(self) -> int:
        return self.count

    def __iter__(self):
        if self.folder is None:
            yield from self._held
            return
        for k in range(self.count):
            with open(self.folder / f"piece_{k}.pkl", "rb") as f:
                yield pickle.load(f)


class BuildingsOnDisk:
    """Buildings too many to hold (a city's, modelled block by block), kept on disk a
    batch at a time and read back a batch at a time: iterating gives them in the order
    they were added, holding one batch. :func:`write_model_run` iterates them a few times.

    Parameters
    ----------
    folder : path
        Where the batches are kept (one pickle each); made if missing.
    """

    def __init__(self, folder):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.files: list[Path] = []
        self.count = 0

    def extend(self, buildings: list[Building]) -> None:
        """Keep ``buildings`` as the next batch (as a list extends itself)."""
        path = self.folder / f"batch_{len(self.files)}.pickle"
        with open(path, "wb") as f:
            pickle.dump(buildings, f, protocol=pickle.HIGHEST_PROTOCOL)
        self.files.append(path)
        self.count += len(buildings)

    def __len__(self) -> int:
        return self.count

    def __iter__(self):
        for path in self.files:
            with open(path, "rb") as f:
                batch = pickle.load(f)
            yield from batch


@dataclass
class Building:
    """One modelled building.

    Attributes
    ----------
    id : str
        Unique in the run; names its files.
    mesh : Surface
        Closed and outward-oriented where the path manages it (``watertight`` says).
    lod : str
        CityJSON level of detail: "1.3" for flat multi-level tops, "2.2" for roof planes.
    footprint : shapely geometry or None
        The outline the building stands on, world metres.
    roof_type : str or None
        One of :data:`modeling.shared.roof_types.ROOF_TYPES`.
    planes : (P, 4) float
        Roof planes (n, d) with unit normal n (n_z > 0), n . X + d = 0.
    plane_areas : (P,) float
        Horizontal area of each plane's faces, square metres.
    base_z, eave_z, ridge_z : float
        Floor, lowest eave and highest roof point, metres.
    watertight : bool or None
        Whether the mesh is closed, outward and free of self-intersections, if the path
        checked it (None: checked when written).
    record : dict
        What else the path says of it (written after the common keys).
    lods : {lod: Surface}
        The same building at other levels of detail the path makes (model.city.json
        writes each beside ``mesh``).
    """

    id: str
    mesh: Surface
    lod: str
    footprint: object = None
    roof_type: str | None = None
    planes: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    plane_areas: np.ndarray = field(default_factory=lambda: np.empty(0))
    base_z: float = float("nan")
    eave_z: float = float("nan")
    ridge_z: float = float("nan")
    watertight: bool | None = None
    record: dict = field(default_factory=dict)
    lods: dict = field(default_factory=dict)

    def common_record(self) -> dict:
        """The keys every path's buildings share in model.json (``BUILDING_KEYS``)."""
        m = self.mesh
        if self.watertight is None:
            self.watertight = is_watertight(m.vertices, m.triangles)
        return {
            "id": self.id,
            "lod": self.lod,
            "mesh": f"buildings/{self.id}.ply",
            "footprint": mapping(self.footprint) if self.footprint is not None else None,
            "roof_type": self.roof_type,
            "planes": [
                {
                    "normal": p[:3].round(5).tolist(),
                    "offset": round(float(p[3]), 4),
                    "area_m2": round(float(a), 2),
                }
                for p, a in zip(self.planes, self.plane_areas, strict=True)
            ],  # fmt: skip
            "base_z": _rounded(self.base_z),
            "eave_z": _rounded(self.eave_z),
            "ridge_z": _rounded(self.ridge_z),
            "faces": int(len(m.triangles)),
            "watertight": self.watertight,
        }


@dataclass
class ModelRun:
    """What a modeling path returns: everything :func:`write_model_run` writes.

    Attributes
    ----------
    method : str
        The path's registered name.
    options : dataclass instance
        The options it ran with (model.json's ``parameters``).
    buildings : list of Building or BuildingsOnDisk
    crs : rasterio CRS or None
    grid : Grid or None
        The grid of ``dtm`` and ``rasters``.
    dtm : (H, W) float or None
        The ground the buildings stand on, metres, NaN unknown.
    dsm : (H, W) float, RasterWindows or None
        The heights the path modelled, metres, NaN unknown: each building's ``rmse_m`` in
        model.city.json is the model's RMS distance to them, vertically (read in the
        building's window).
    ground : Surface, SurfacePieces, TexturedPieces or None
        The ground as a mesh (default: none written).
    rasters : {name: ((H, W) or (B, H, W) array, nodata)}
        The path's own rasters on ``grid``.
    raster_files : {name: path}
        Rasters on ``grid`` already on disk (GeoTIFFs), copied into the run as NAME.tif:
        those a path in blocks does not hold whole ("dtm" among them in place of ``dtm``).
    preview : (h, w, 3) uint8 or None
    stages : {stage: {"wall_s": float, "peak_memory_mb": float}}
    inputs : dict
        What it read (paths as strings).
    parameters : dict
        Parameters decided at run time (they update the options' values).
    counts : dict
        Counts beside buildings, faces and watertight.
    record : dict
        The path's own sections of model.json.
    """

    method: str
    options: object
    buildings: list[Building]
    crs: object = None
    grid: Grid | None = None
    dtm: np.ndarray | None = None
    dsm: np.ndarray | None = None
    ground: Surface | SurfacePieces | TexturedPieces | None = None
    rasters: dict = field(default_factory=dict)
    raster_files: dict = field(default_factory=dict)
    preview: np.ndarray | None = None
    stages: dict = field(default_factory=dict)
    inputs: dict = field(default_factory=dict)
    parameters: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)
    record: dict = field(default_factory=dict)

    def to_record(self, command: list[str] | None, buildings, counts: dict) -> dict:
        """model.json as a dict (without the write stage), with ``buildings`` (their
        entries, or what stands for them) and their ``counts`` (:func:`building_counts`)
        given; ``command``: the command line that made the run, if any."""
        return {
            "schema": SCHEMA,
            "method": self.method,
            "provenance": provenance(command),
            "crs": crs_text(self.crs),
            "parameters": {**options_record(self.options), **self.parameters},
            "inputs": self.inputs,
            "buildings": buildings,
            "counts": {**counts, **self.counts},
            "stages": dict(self.stages),
            **self.record,
        }


def building_record(b: Building) -> dict:
    """``b``'s entry in model.json: the common keys, then the path's own."""
    return {**b.common_record(), **b.record}


def building_counts(records) -> dict:
    """model.json's ``counts`` of buildings, faces and watertight ones, of the buildings'
    entries (any iterable: each is counted as it comes)."""
    counts = {"buildings": 0, "faces": 0, "watertight": 0}
    for r in records:
        counts["buildings"] += 1
        counts["faces"] += int(r["faces"])
        counts["watertight"] += int(bool(r["watertight"]))
    return counts


def write_model_run(
    run: ModelRun, out: str | Path, *, overwrite: bool = False, command: list[str] | None = None
) -> dict:
    """Write ``run`` as a run folder (atomically: all of it or nothing); return model.json's
    record as a reader of it sees it, but for its buildings, which :func:`model_buildings`
    reads back one at a time (a city's are hundreds of megabytes as Python objects).
    ``command`` is the command line that made it, for its record. The buildings are
    written one at a time (:class:`BuildingsOnDisk` are never all in memory).

    Raises
    ------
    WorkbenchError
        ``out`` exists and ``overwrite`` is False.
    """
    out = Path(out)
    timer = StageTimer()
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        with timer.stage("write"):
            records, counts = _write_files(run, tmp)
        record = run.to_record(command, _RECORDS, counts)
        record["stages"].update(timer.stages)
        # the command's own peak, every path alike (a path with workers adds theirs)
        record.setdefault("peak_memory_mb", round(peak_memory_mb(), 1))
        _write_model_json(tmp / "model.json", record, records)
    if not counts["buildings"]:
        log.warning("%s: the model holds no building", out)
    del record["buildings"]
    return json.loads(json.dumps(record))  # as a reader of model.json sees it


def model_buildings(folder: str | Path):
    """Each building's record of a run folder's model.json, one at a time.

    The writer puts each record on lines of its own, opened by ``"  {"`` and closed by
    ``"  }"`` (:func:`_write_model_json`), so they are parsed one by one; a model.json
    of another layout (edited by hand) is read whole.

    Yields
    ------
    dict
        The record, as ``json.load(model.json)["buildings"][i]`` is.
    """
    path = Path(folder) / "model.json"
    with open(path) as f:
        complete, done = yield from _records_one_by_one(f)
    if not complete:  # not the writer's layout: read whole
        yield from json.loads(path.read_text()).get("buildings", [])[done:]


def _records_one_by_one(f):
    """Yield the building records of the open model.json ``f`` as the writer lays them
    out; return whether that layout held to the list's end, and how many were read."""
    for line in f:
        if line.startswith(' "buildings": ['):
            break
    else:
        return False, 0
    if line.rstrip().rstrip(",").endswith("[]"):
        return True, 0
    done, lines = 0, []
    for line in f:
        if line == "  {\n":
            lines = [line]
        elif line in ("  }\n", "  },\n"):
            yield json.loads("".join(lines) + "}")
            done, lines = done + 1, []
        elif lines:
            lines.append(line)
        else:
            return line.startswith(" ]"), done
    return False, done


_RECORDS = "\u0000buildings\u0000"  # where the buildings' records go in model.json's text


def _write_model_json(path: Path, record: dict, records) -> None:
    """model.json as ``json.dumps(record, indent=1)`` would write it with the buildings'
    records (an open text file of them, each ``indent=1`` JSON on its own lines, separated
    by ``,\\n``) in place of ``_RECORDS``."""
    head, tail = json.dumps(record, indent=1).split(json.dumps(_RECORDS))
    records.seek(0)
    with open(path, "w") as f:
        f.write(head)
        if records.read(1):
            records.seek(0)
            f.write("[\n")
            shutil.copyfileobj(records, f)
            f.write("\n ]")
        else:
            f.write("[]")
        f.write(tail + "\n")
    records.close()


def _write_files(run: ModelRun, tmp: Path):
    """Every file of the run but model.json, one building at a time; returns the buildings'
    records for model.json (a spooled text file, :func:`_write_model_json`) and their
    counts."""
    bdir = tmp / "buildings"
    bdir.mkdir()
    records = tempfile.SpooledTemporaryFile(max_size=SPOOL_BYTES, mode="w+", dir=tmp)

    def written(cities: CityModelWriter):  # each building's files; its entry as it goes
        for b in run.buildings:
            _write_surface(bdir, b.id, b.mesh, f"building_{b.id}")
            r = building_record(b)
            text = json.dumps(r, indent=1).replace("\n", "\n  ")
            records.write((",\n  " if records.tell() else "  ") + text)
            cities.add(b, rms_to_heights(b, run.dsm, run.grid))
            yield r

    with open(tmp / "model.city.json", "w") as city:
        cities = CityModelWriter(city, run.method, run.crs, city_origin(run.buildings), tmp)
        counts = building_counts(written(cities))
        cities.finish()

    def parts():  # material, mesh, its texture's path
        for b in run.buildings:
            yield f"building_{b.id}", b.mesh, f"buildings/{b.id}.png"
        yield from _ground_parts(run.ground)

    if isinstance(run.ground, TexturedPieces):
        (tmp / "ground").mkdir()
        for _, s, png in _ground_parts(run.ground):
            write_rgb(tmp / png, s.texture.image)
        _write_scene(tmp, lambda: _ground_parts(run.ground), stem="ground")
    elif run.ground is not None:
        _write_surface(tmp, "ground", run.ground, "ground")
    _write_scene(tmp, parts)
    if run.dtm is not None and run.grid is not None:
        write_raster(tmp / "dtm.tif", run.dtm.astype(np.float32), run.grid, run.crs)
    for name, (data, nodata) in run.rasters.items():
        write_raster(tmp / f"{name}.tif", data, run.grid, run.crs, nodata=nodata)
    for name, path in run.raster_files.items():
        shutil.copyfile(path, tmp / f"{name}.tif")
    preview = run.preview if run.preview is not None else np.full((64, 64, 3), 255, np.uint8)
    write_rgb(tmp / "preview.png", preview)
    return records, counts


def _colours(s: Surface) -> np.ndarray:
    if s.vertex_colors is not None:
        return np.asarray(s.vertex_colors, np.uint8)
    return np.full((len(s.vertices), 3), 128, np.uint8)


def _material_colour(s: Surface | SurfacePieces) -> tuple[int, int, int]:
    if isinstance(s, SurfacePieces):
        if not s.colour_medians:
            return _GREY
        return tuple(int(v) for v in np.median(s.colour_medians, axis=0))
    if s.vertex_colors is None or not len(s.vertex_colors):
        return _GREY
    return tuple(int(v) for v in np.median(s.vertex_colors, axis=0))


def _pieces(s: Surface | SurfacePieces, colours: bool = True):
    """The mesh's pieces for :func:`~.meshio.write_ply_pieces` (grey where uncoloured;
    no colours with ``colours`` False)."""
    if isinstance(s, SurfacePieces):
        yield from s.pieces()
    else:
        yield s.vertices, s.triangles, _colours(s) if colours else None


def _counts(s: Surface | SurfacePieces) -> tuple[int, int]:
    if isinstance(s, SurfacePieces):
        return s.n_vertices, s.n_triangles
    return len(s.vertices), len(s.triangles)


def _write_surface(folder: Path, name: str, s: Surface | SurfacePieces, material: str) -> None:
    """``name``.ply with vertex colours; ``name``.obj|.mtl, with ``name``.png if textured."""
    if isinstance(s, SurfacePieces):  # never whole in memory
        write_ply_pieces(folder / f"{name}.ply", s.pieces, *_counts(s), colours=True)
        write_mtl(folder / f"{name}.mtl", {material: _material_colour(s)})
        write_obj_pieces(folder / f"{name}.obj", s.pieces, s.n_triangles, material=material,
                         mtllib=f"{name}.mtl")  # fmt: skip
        return
    write_ply(folder / f"{name}.ply", s.vertices, s.triangles, vertex_colors=_colours(s))
    if s.texture is not None:
        write_rgb(folder / f"{name}.png", s.texture.image)
        write_mtl(folder / f"{name}.mtl", {material: (255, 255, 255)}, {material: f"{name}.png"})
        write_obj(
            folder / f"{name}.obj", s.vertices, s.triangles, material=material,
            mtllib=f"{name}.mtl", uvs=s.texture.uvs,
        )  # fmt: skip
        return
    write_mtl(folder / f"{name}.mtl", {material: _material_colour(s)})
    write_obj(
        folder / f"{name}.obj", s.vertices, s.triangles, vertex_colors=s.vertex_colors,
        material=material, mtllib=f"{name}.mtl",
    )  # fmt: skip


def _ground_parts(ground):
    """The ground's parts of the scene: (material, mesh, its texture's path) each."""
    if isinstance(ground, TexturedPieces):
        for k, s in enumerate(ground):
            yield f"ground_{k}", s, f"ground/{k}.png"
    elif ground is not None:
        yield "ground", ground, "ground.png"


def _write_scene(tmp: Path, parts, stem: str = "scene") -> None:
    """``stem``.ply (vertex colours) and ``stem``.obj|.mtl (default scene.*): textured when
    every part is. Written part by part, each part piece by piece, so that the scene is
    never whole in memory; ``parts()`` gives the parts, (material, Surface or
    SurfacePieces, texture path) each, and is called once for each pass over them."""
    names, n_vertices, n_triangles, textured, colours, runs = [], 0, 0, True, {}, []
    for name, s, png in parts():
        v, t = _counts(s)
        n_vertices += v
        n_triangles += t
        runs.append((name, t))
        names.append((name, png))
        textured &= s.texture is not None
        colours[name] = _material_colour(s)

    def pieces(colours: bool = True):
        for _, s, _ in parts():
            yield from _pieces(s, colours)

    write_ply_pieces(tmp / f"{stem}.ply", pieces, n_vertices, n_triangles, colours=True)
    if names and textured:
        white = {name: (255, 255, 255) for name, _ in names}
        write_mtl(tmp / f"{stem}.mtl", white, dict(names))
        write_obj_pieces(tmp / f"{stem}.obj", lambda: pieces(colours=False), n_triangles,
                         material=runs, mtllib=f"{stem}.mtl",
                         uvs=lambda: (s.texture.uvs for _, s, _ in parts()))  # fmt: skip
        return
    write_mtl(tmp / f"{stem}.mtl", colours)
    write_obj_pieces(tmp / f"{stem}.obj", pieces, n_triangles, material=runs, mtllib=f"{stem}.mtl")


def _rounded(v: float) -> float | None:
    return round(float(v), 3) if v is not None and np.isfinite(v) else None


def crs_text(crs) -> str | None:
    if crs is None:
        return None
    return crs.to_string() if crs.to_epsg() else crs.to_wkt()


def stage_record(seconds: float) -> dict:
    """One stage's entry of ``stages``: its wall time and the process's peak memory."""
    return {"wall_s": round(seconds, 3), "peak_memory_mb": round(peak_memory_mb(), 1)}

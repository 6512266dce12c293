"""The one writer of model runs, on hand-made runs."""

import json

import numpy as np
import open3d as o3d
import pytest
from shapely.geometry import box

from modeling.shared.roof_mesh import extrude_faces
from workbench.imageio import read_rgb
from workbench.meshes import read_mesh
from workbench.model_run import (
    BUILDING_KEYS,
    Building,
    BuildingsOnDisk,
    ModelRun,
    Surface,
    Texture,
    TexturedPieces,
    _records_one_by_one,
    model_buildings,
    write_model_run,
)
from workbench.options import option
from workbench.raster import Grid, read_raster


def _box_building(bid: str, x0: float, texture: bool = False) -> Building:
    """A 10 m x 6 m flat-roofed box, 8 m tall on ground at 2 m."""
    footprint = box(x0, 0, x0 + 10, 6)
    plane = np.array([0.0, 0.0, 1.0, -10.0])
    V, T = extrude_faces([footprint], [plane], 2.0)
    colours = np.tile(np.array([[200, 10, 10]], np.uint8), (len(V), 1))
    tex = None
    if texture:
        tex = Texture(np.full((4, 4, 3), 90, np.uint8), np.full((len(T), 3, 2), 0.5))
    return Building(
        bid, Surface(V, T, colours, tex), lod="1.3", footprint=footprint, roof_type="flat",
        planes=plane[None], plane_areas=np.array([60.0]), base_z=2.0, eave_z=10.0,
        ridge_z=10.0, record={"extra": 1},
    )  # fmt: skip


from dataclasses import dataclass  # noqa: E402


@dataclass
class _Options:
    size_m: float = option(1.0, "a size", unit="m")


def _run(buildings, **kw) -> ModelRun:
    grid = Grid(-5.0, 20.0, 1.0, 40, 30)
    return ModelRun("boxes", _Options(), buildings, grid=grid,
                    dtm=np.full(grid.shape, 2.0), **kw)  # fmt: skip


def test_a_run_becomes_its_folder(tmp_path):
    run = _run([_box_building("a", 0.0), _box_building("b", 15.0)],
               rasters={"class": (np.ones((30, 40), np.uint8), 0)})  # fmt: skip
    record = write_model_run(run, tmp_path / "run")
    out = tmp_path / "run"
    doc = json.loads((out / "model.json").read_text())
    assert record == {k: v for k, v in doc.items() if k != "buildings"}  # but its buildings
    assert record["parameters"] == {"size_m": 1.0} and record["method"] == "boxes"
    assert record["counts"] == {"buildings": 2, "faces": 24, "watertight": 2}
    buildings = list(model_buildings(out))  # read one at a time
    assert buildings == doc["buildings"] and [b["id"] for b in buildings] == ["a", "b"]
    a = buildings[0]
    assert list(a) == [*BUILDING_KEYS, "extra"]
    assert a["mesh"] == "buildings/a.ply" and a["faces"] == 12 and a["watertight"]
    assert a["planes"] == [{"normal": [0.0, 0.0, 1.0], "offset": -10.0, "area_m2": 60.0}]
    assert a["footprint"]["type"] == "Polygon"
    mesh = o3d.io.read_triangle_mesh(str(out / "buildings" / "a.ply"))
    assert len(mesh.triangles) == 12
    assert np.allclose(np.asarray(mesh.vertex_colors), [200 / 255, 10 / 255, 10 / 255])
    assert "Kd 0.784 0.039 0.039" in (out / "buildings" / "a.mtl").read_text()
    scene_v, scene_t = read_mesh(out / "scene.obj")
    assert len(scene_t) == 24 and not (out / "ground.ply").exists()  # no ground given
    dtm, grid, _ = read_raster(out / "dtm.tif")
    assert dtm.dtype == np.float32 and grid == run.grid and (dtm == 2.0).all()
    cls, _, _ = read_raster(out / "class.tif")
    assert (cls == 1).all()
    assert "write" in record["stages"] and (out / "preview.png").exists()


def test_textured_runs_carry_their_atlases(tmp_path):
    atlas = Texture(np.zeros((2, 2, 3), np.uint8), np.zeros((1, 3, 2)))
    corners = np.array([[0, 0, 2], [30, 0, 2], [0, 20, 2.0]])
    ground = Surface(corners, np.array([[0, 1, 2]]), texture=atlas)
    run = _run([_box_building("a", 0.0, texture=True)], ground=ground)
    write_model_run(run, tmp_path / "run")
    out = tmp_path / "run"
    for name in ("buildings/a.png", "ground.png", "ground.obj", "ground.ply"):
        assert (out / name).exists(), name
    mtl = (out / "scene.mtl").read_text()
    assert "map_Kd buildings/a.png" in mtl and "map_Kd ground.png" in mtl
    assert "vt 0.500000 0.500000" in (out / "scene.obj").read_text()


def test_a_ground_textured_in_tiles_has_a_material_and_an_image_per_tile(tmp_path):
    """Two tiles, each its own image (on disk in pieces, as a city's ground waits): the
    ground and the scene each get a material per tile, mapped to ground/K.png, and
    every tile's triangles with their texture coordinates."""
    pieces = TexturedPieces(tmp_path / "pieces")
    (tmp_path / "pieces").mkdir()
    for k in range(2):
        image = np.full((2, 2, 3), 60 * (k + 1), np.uint8)
        corners = np.array([[30.0 * k, 0, 2], [30.0 * k + 30, 0, 2], [30.0 * k, 20, 2]])
        uvs = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 0.25 * (k + 1)]]])
        pieces.add(Surface(corners, np.array([[0, 1, 2]]), np.full((3, 3), 60 * (k + 1)),
                           Texture(image, uvs)))  # fmt: skip
    run = _run([_box_building("a", 0.0, texture=True)], ground=pieces)
    write_model_run(run, tmp_path / "run")
    out = tmp_path / "run"
    for k in range(2):
        image = read_rgb(out / "ground" / f"{k}.png")
        assert (image == 60 * (k + 1)).all()
    for stem in ("ground", "scene"):
        mtl = (out / f"{stem}.mtl").read_text()
        assert "map_Kd ground/0.png" in mtl and "map_Kd ground/1.png" in mtl
        obj = (out / f"{stem}.obj").read_text()
        assert "usemtl ground_0" in obj and "usemtl ground_1" in obj
        assert "vt 0.000000 0.250000" in obj and "vt 0.000000 0.500000" in obj
    v, t = read_mesh(out / "ground.ply")
    assert len(t) == 2 and v[:, 0].max() == 60.0
    mesh = o3d.io.read_triangle_mesh(str(out / "ground.obj"), True)
    assert len(mesh.textures) == 2 and len(mesh.triangles) == 2


def test_a_failed_write_leaves_nothing(tmp_path):
    run = _run([_box_building("a", 0.0)], rasters={"bad": (np.ones((3, 3), np.uint8), 0)})
    with pytest.raises(Exception):  # noqa: B017 - the raster does not fit the grid
        write_model_run(run, tmp_path / "run")
    assert not (tmp_path / "run").exists() and not list(tmp_path.iterdir())


def test_buildings_kept_on_disk_write_the_same_folder(tmp_path):
    def buildings():
        return [_box_building(k, x) for k, x in (("a", 0.0), ("b", 15.0), ("c", 30.0))]

    kept = BuildingsOnDisk(tmp_path / "kept")
    kept.extend(buildings()[:2])
    kept.extend([])  # a block with none
    kept.extend(buildings()[2:])
    assert len(kept) == 3 and [b.id for b in kept] == ["a", "b", "c"]
    assert [b.id for b in kept] == ["a", "b", "c"]  # read again from disk
    records = {}
    for name, held in (("list", buildings()), ("disk", kept)):
        records[name] = write_model_run(_run(held), tmp_path / name)
        for r in (records[name], json.loads((tmp_path / name / "model.json").read_text())):
            assert r.pop("stages") and r.pop("peak_memory_mb") > 0
    assert records["list"] == records["disk"]
    assert records["disk"]["counts"] == {"buildings": 3, "faces": 36, "watertight": 3}
    files = sorted(p.relative_to(tmp_path / "list") for p in (tmp_path / "list").rglob("*"))
    assert files == sorted(p.relative_to(tmp_path / "disk") for p in (tmp_path / "disk").rglob("*"))
    for f in files:
        if f.name != "model.json" and f.is_file():
            assert (tmp_path / "list" / f).read_bytes() == (tmp_path / "disk" / f).read_bytes(), f
    # model.json, written a building at a time, is what json.dumps(indent=1) writes
    text = (tmp_path / "disk" / "model.json").read_text()
    assert text == json.dumps(json.loads(text), indent=1) + "\n"


def test_an_empty_run_writes_an_empty_list(tmp_path):
    write_model_run(_run([]), tmp_path / "run")
    text = (tmp_path / "run" / "model.json").read_text()
    assert '"buildings": [],' in text and text == json.dumps(json.loads(text), indent=1) + "\n"
    assert list(model_buildings(tmp_path / "run")) == []
    city = json.loads((tmp_path / "run" / "model.city.json").read_text())
    assert city["CityObjects"] == {} and city["vertices"] == []


def test_buildings_are_read_back_from_a_model_json_of_any_layout(tmp_path):
    write_model_run(_run([_box_building("a", 0.0), _box_building("b", 15.0)]), tmp_path / "run")
    path = tmp_path / "run" / "model.json"
    doc = json.loads(path.read_text())
    # the writer's layout is read a record at a time, to the list's end
    with open(path) as f:
        assert _drained(_records_one_by_one(f)) == (doc["buildings"], (True, 2))
    path.write_text(json.dumps(doc))  # one line, as an editor or another tool may save it
    with open(path) as f:
        assert _drained(_records_one_by_one(f)) == ([], (False, 0))
    assert list(model_buildings(tmp_path / "run")) == doc["buildings"]
    path.write_text(json.dumps(doc, indent=4))
    assert list(model_buildings(tmp_path / "run")) == doc["buildings"]


def _drained(gen) -> tuple[list, object]:
    """A generator's items and its return value."""
    items = []
    while True:
        try:
            items.append(next(gen))
        except StopIteration as stop:
            return items, stop.value

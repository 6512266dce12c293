"""Move a written sample to real coordinates: ``workbench sample ... --origin E N --crs``.

The synthetic city is built around its CRS's zero (a local transverse Mercator), where
float32 loses nothing. Real data lies at eastings of hundreds of kilometres and northings
of thousands (UTM 31N: 500,000 and 5,700,000 m), where float32 resolves half a metre. This
translates every georeferenced part of a sample by (E, N) and names another CRS for it, so
that every command can be run, and tested, on the same city far from its origin: the
views and depth maps stay as they are (they are camera-relative), the cameras move.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import rasterio
import shapely
from rasterio.crs import CRS

from workbench.footprints import footprints_geojson, read_footprints
from workbench.meshio import read_ply, write_ply
from workbench.raster import Grid, read_raster, write_raster


def relocate_sample(folder: Path, origin: tuple[float, float], crs: CRS) -> None:
    """Translate the sample in ``folder`` by ``origin`` (E, N metres) and label it ``crs``.

    A camera x_cam = R X + t seeing X + o is x_cam = R (X + o) + (t - R o).
    """
    shift = np.array([origin[0], origin[1], 0.0])
    scene_json = folder / "scene.json"
    doc = json.loads(scene_json.read_text())
    doc["crs"] = crs.to_wkt()
    x0, y0, x1, y1 = doc["bounds"]
    doc["bounds"] = [x0 + shift[0], y0 + shift[1], x1 + shift[0], y1 + shift[1]]
    for view in doc["images"]:
        _move_camera(view, shift)
    scene_json.write_text(json.dumps(doc, indent=1) + "\n")
    cameras = folder / "truth" / "cameras.json"
    if cameras.exists():
        true = json.loads(cameras.read_text())
        for cam in true["cameras"]:
            _move_camera(cam, shift)
        cameras.write_text(json.dumps(true, indent=1) + "\n")
    for raster in [*sorted((folder / "truth").glob("*.tif")), folder / "training" / "labels.tif"]:
        if raster.exists():
            _move_raster(raster, shift, crs)
    mesh = folder / "truth" / "mesh.ply"
    if mesh.exists():
        vertices, triangles, props = read_ply(mesh)
        write_ply(mesh, vertices + shift, triangles, face_properties=props)
    for name in ("footprints_gis.geojson", "truth/footprints.geojson"):
        path = folder / name
        if path.exists():
            items = [
                {"id": f.id, "polygon": shapely.affinity.translate(f.polygon, *shift[:2]),
                 "properties": f.properties}
                for f in read_footprints(path)
            ]  # fmt: skip
            path.write_text(json.dumps(footprints_geojson(items, crs), indent=1) + "\n")
    buildings = folder / "truth" / "buildings.json"
    if buildings.exists():
        doc = json.loads(buildings.read_text())
        for b in doc["buildings"]:
            b["footprint"] = (np.asarray(b["footprint"]) + shift[:2]).round(4).tolist()
            for wing in b.get("wings", []):
                wing["center"] = (np.asarray(wing["center"]) + shift[:2]).round(4).tolist()
        buildings.write_text(json.dumps(doc, indent=1) + "\n")
    meta_path = folder / "sample.json"
    meta = json.loads(meta_path.read_text())
    meta["origin"] = {"easting": origin[0], "northing": origin[1], "crs": crs.to_string()}
    meta_path.write_text(json.dumps(meta, indent=1) + "\n")


def _move_camera(cam: dict, shift: np.ndarray) -> None:
    R = np.asarray(cam["R"], np.float64)
    cam["t"] = (np.asarray(cam["t"], np.float64) - R @ shift).round(9).tolist()


def _move_raster(path: Path, shift: np.ndarray, crs: CRS) -> None:
    data, grid, _ = read_raster(path)
    with rasterio.open(path) as src:
        nodata = src.nodata
        descriptions = list(src.descriptions) if any(src.descriptions) else None
    moved = Grid(grid.xmin + shift[0], grid.ymax + shift[1], grid.gsd, grid.width, grid.height)
    write_raster(path, data, moved, crs, nodata=nodata, descriptions=descriptions)

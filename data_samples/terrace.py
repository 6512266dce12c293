"""A terraced block as airborne LiDAR tiles: the sample of real coordinates and long rows.

Two rows of attached houses back to back, each house with a roof of its own (gable,
hipped, mansard, shed, flat) and eaves that differ by up to a storey, form one connected
building region of about 2,300 m^2: the shape that made the dense prototype clustering
quadratic. The block is scanned as an airborne laser would: parallel scan lines, returns
along them, a few centimetres of noise, ASPRS classes 2 (ground) and 6 (building), and
written as LAZ tiles in a projected CRS far from its origin (UTM 31N by default), so that
the merging of tiles, the CRS from the LAS header and float32 work in a local origin are
all exercised. The truth (DSM, DTM, classes, building ids) is written beside the tiles.

    python -m data_samples.terrace OUT [--seed 0] [--houses 14] [--origin E N] [--crs EPSG:32631]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from rasterio.crs import CRS

from workbench.raster import Grid, write_raster

from .roofs import Wing, wing_roof_faces

ROOFS = ("gable", "gable", "hipped", "mansard", "shed", "flat")
LAS_GROUND, LAS_BUILDING = 2, 6


def terrace_houses(rng: np.random.Generator, houses: int = 14, depth: float = 11.0):
    """Two rows of ``houses`` attached houses, back to back, in local metres.

    Returns
    -------
    list of (Wing, roof type, eave height above the ground, pitch in degrees); the rows
    run along x from 0, the first row's backs on y = 0 facing south, the second's north.
    """
    out = []
    for row in (-1, 1):
        x = 0.0
        for _ in range(houses):
            width = float(rng.uniform(6.0, 8.5))
            wing = Wing(x + width / 2, row * depth / 2, depth / 2, width / 2, np.pi / 2)
            roof = str(rng.choice(ROOFS))
            eave = float(rng.choice([5.5, 6.0, 6.5, 8.5, 9.0]))
            out.append((wing, roof, eave, float(rng.uniform(30.0, 45.0))))
            x += width
    return out


def ground_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A gently sloping street, metres: 0.4 % east, a 0.3 m wave north."""
    return 1.5 + 0.004 * x + 0.3 * np.sin(y / 25.0)


def surface_height(houses, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Height of the scene's top surface and the house (1-based, 0 ground) at ``x, y``.

    Every roof here is convex, so within its house it is the lower envelope of its planes.
    """
    z = ground_height(x, y)
    owner = np.zeros(np.shape(x), np.int32)
    for k, (wing, roof, eave, pitch) in enumerate(houses, start=1):
        c, s = np.cos(wing.angle), np.sin(wing.angle)
        along = c * (x - wing.cx) + s * (y - wing.cy)
        across = -s * (x - wing.cx) + c * (y - wing.cy)
        inside = (np.abs(along) <= wing.a) & (np.abs(across) <= wing.b)
        if not inside.any():
            continue
        base = ground_height(wing.cx, wing.cy)
        faces = wing_roof_faces(wing, roof, base + eave, pitch_deg=pitch)
        xi, yi = x[inside], y[inside]
        roof_z = np.min([f.plane[0] * xi + f.plane[1] * yi + f.plane[2] for f in faces], axis=0)
        z[inside] = roof_z
        owner[inside] = k
    return z, owner


def scan_lines(
    bounds: tuple[float, float, float, float],
    rng: np.random.Generator,
    line_spacing: float = 0.45,
    point_spacing: float = 0.18,
    angle_deg: float = 3.0,
) -> np.ndarray:
    """(N, 2) return positions of parallel scan lines across ``bounds`` (x0, y0, x1, y1):
    lines ``line_spacing`` apart, returns ``point_spacing`` apart along them, tilted
    ``angle_deg`` from north, with a little jitter: the pattern that leaves rows of empty
    cells when the cell size is the nearest-return spacing."""
    x0, y0, x1, y1 = bounds
    span = np.hypot(x1 - x0, y1 - y0)
    u = np.arange(-span / 2, span / 2, line_spacing)  # across the lines
    v = np.arange(-span / 2, span / 2, point_spacing)  # along them
    U, V = np.meshgrid(u, v)
    a = np.radians(angle_deg)
    x = (x0 + x1) / 2 + np.cos(a) * U - np.sin(a) * V
    y = (y0 + y1) / 2 + np.sin(a) * U + np.cos(a) * V
    xy = np.column_stack([x.ravel(), y.ravel()]) + rng.normal(0, 0.02, (U.size, 2))
    inside = (xy[:, 0] >= x0) & (xy[:, 0] < x1) & (xy[:, 1] >= y0) & (xy[:, 1] < y1)
    return xy[inside]


def write_terrace(
    out: Path,
    seed: int = 0,
    houses: int = 14,
    origin: tuple[float, float] = (500000.0, 5700000.0),
    crs: str = "EPSG:32631",
    tiles: int = 2,
    gsd: float = 0.25,
) -> dict:
    """Write ``out/tiles/*.laz`` (``tiles`` tiles split along x) and ``out/truth/``.

    Returns
    -------
    The record written to ``out/terrace.json``.
    """
    import laspy
    import pyproj

    rng = np.random.default_rng(seed)
    block = terrace_houses(rng, houses)
    length = max(w.cx + w.b for w, *_ in block)
    bounds = (-15.0, -25.0, length + 15.0, 25.0)
    xy = scan_lines(bounds, rng)
    z, owner = surface_height(block, xy[:, 0], xy[:, 1])
    z = z + rng.normal(0, 0.03, len(z))
    cls = np.where(owner > 0, LAS_BUILDING, LAS_GROUND).astype(np.uint8)
    (out / "tiles").mkdir(parents=True, exist_ok=True)
    cuts = np.linspace(bounds[0], bounds[2], tiles + 1)
    names = []
    for t in range(tiles):
        sel = (xy[:, 0] >= cuts[t]) & (xy[:, 0] < cuts[t + 1] + (t == tiles - 1))
        header = laspy.LasHeader(point_format=1, version="1.4")
        header.offsets = [origin[0], origin[1], 0.0]
        header.scales = [0.001, 0.001, 0.001]
        header.add_crs(pyproj.CRS.from_user_input(crs))
        las = laspy.LasData(header)
        las.x = xy[sel, 0] + origin[0]
        las.y = xy[sel, 1] + origin[1]
        las.z = z[sel]
        las.classification = cls[sel]
        las.intensity = np.where(cls[sel] == LAS_BUILDING, 900, 1500).astype(np.uint16)
        name = f"tiles/terrace_{t}.laz"
        las.write(out / name)
        names.append(name)
    grid = Grid.from_bounds(
        bounds[0] + origin[0], bounds[1] + origin[1], bounds[2] + origin[0],
        bounds[3] + origin[1], gsd,
    )  # fmt: skip
    X, Y = grid.cell_centers()
    dsm, ids = surface_height(block, X - origin[0], Y - origin[1])
    dtm = ground_height(X - origin[0], Y - origin[1])
    (out / "truth").mkdir(exist_ok=True)
    crs_obj = CRS.from_user_input(crs)
    write_raster(out / "truth" / "dsm.tif", dsm.astype(np.float32), grid, crs_obj)
    write_raster(out / "truth" / "dtm.tif", dtm.astype(np.float32), grid, crs_obj)
    write_raster(
        out / "truth" / "class.tif", np.where(ids > 0, 4, 1).astype(np.uint8), grid, crs_obj
    )
    write_raster(out / "truth" / "building_id.tif", ids.astype(np.int32), grid, crs_obj)
    record = {
        "seed": seed,
        "crs": crs,
        "origin": list(origin),
        "tiles": names,
        "points": int(len(xy)),
        "houses": [
            {"roof": roof, "eave_m": eave, "pitch_deg": round(pitch, 1), "width_m": 2 * w.b}
            for w, roof, eave, pitch in block
        ],
        "building_area_m2": round(float((ids > 0).sum()) * gsd * gsd, 1),
    }
    (out / "terrace.json").write_text(json.dumps(record, indent=1) + "\n")
    return record


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--houses", type=int, default=14, help="houses per row")
    ap.add_argument("--origin", type=float, nargs=2, default=(500000.0, 5700000.0),
                    metavar=("E", "N"))  # fmt: skip
    ap.add_argument("--crs", default="EPSG:32631")
    args = ap.parse_args(argv)
    rec = write_terrace(args.out, args.seed, args.houses, tuple(args.origin), args.crs)
    print(f"{args.out}: {rec['points']} returns in {len(rec['tiles'])} tiles, "
          f"{rec['building_area_m2']} m2 of roofs")  # fmt: skip


if __name__ == "__main__":
    main()

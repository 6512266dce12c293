"""A sample city scanned as airborne LiDAR: LAZ tiles cut from its truth, for the fusion of
clouds at city scale (``fusion --points`` on many tiles, in blocks).

A survey is delivered as square tiles. Each tile here is scanned as :mod:`.terrace` scans
its block (parallel lines, returns along them, a little jitter) and each return takes
the truth's top surface, class, colour and a brightness as intensity at its cell, with a
few centimetres of noise. Classes are ASPRS codes (2 ground, 3 low vegetation for grass,
5 high vegetation, 6 building); one echo per pulse. The tiles carry the scene's CRS, and
the truth the scene already has (``fusion --points TILES --truth SCENE`` scores them).

Memory follows one tile: the truth is read a tile's window at a time.

    python -m data_samples.lidar SCENE OUT [--tile 250] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from workbench.raster import Grid, raster_header, read_raster

from .terrace import scan_lines

# our classes (1 ground, 2 grass, 3 tree, 4 building) -> ASPRS codes
CLASS_TO_ASPRS = np.array([1, 2, 3, 5, 6], np.uint8)  # 0, no data -> 1, unclassified


def scanned_tile(truth: Path, bounds, rng: np.random.Generator, noise_m: float = 0.03):
    """The returns of one tile: scan lines across ``bounds`` (x0, y0, x1, y1) reading the
    truth's rasters (``truth/{dsm,class,ortho}.tif``) at their cells.

    Returns
    -------
    xyz : (N, 3) float64, metres; cls : (N,) uint8 ASPRS codes; rgb : (N, 3) uint8
    """
    grid = raster_header(truth / "dsm.tif", "truth")[0]
    xy = scan_lines(bounds, rng)
    row, col = grid.cell_index(xy[:, 0], xy[:, 1], clip=True)
    rows = slice(int(row.min()), int(row.max()) + 1)
    cols = slice(int(col.min()), int(col.max()) + 1)
    dsm = read_raster(truth / "dsm.tif", window=(rows, cols))[0][0]
    cls = read_raster(truth / "class.tif", window=(rows, cols))[0][0]
    ortho = read_raster(truth / "ortho.tif", window=(rows, cols))[0]
    r, c = row - rows.start, col - cols.start
    z = dsm[r, c].astype(np.float64)
    seen = np.isfinite(z)
    z = z + rng.normal(0.0, noise_m, len(z))
    xyz = np.column_stack([xy, z])[seen]
    return xyz, CLASS_TO_ASPRS[cls[r, c][seen]], np.moveaxis(ortho, 0, -1)[r, c][seen]


def write_lidar_tiles(scene: Path, out: Path, tile_m: float = 250.0, seed: int = 0) -> dict:
    """Write ``out/*.laz``, one tile per ``tile_m`` square of the scene's truth, and
    ``out/lidar.json``.

    Returns
    -------
    The record written: the tiles, their returns, the scan's spacing.
    """
    import laspy
    import pyproj

    truth = Path(scene) / "truth"
    grid, _, crs = raster_header(truth / "dsm.tif", "truth")
    if crs is None:
        raise ValueError(f"{truth / 'dsm.tif'}: the truth has no CRS for the tiles")
    x0, y0, x1, y1 = grid.bounds
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    tiles, total = [], 0
    for ty in np.arange(y0, y1, tile_m):
        for tx in np.arange(x0, x1, tile_m):
            bounds = (tx, ty, min(tx + tile_m, x1), min(ty + tile_m, y1))
            xyz, cls, rgb = scanned_tile(truth, bounds, rng)
            header = laspy.LasHeader(point_format=7, version="1.4")  # RGB, WKT CRS
            header.offsets = [np.floor(tx), np.floor(ty), 0.0]
            header.scales = [0.001, 0.001, 0.001]
            header.add_crs(pyproj.CRS.from_wkt(crs.to_wkt()))
            las = laspy.LasData(header)
            las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            las.classification = cls
            las.red, las.green, las.blue = (rgb[:, k].astype(np.uint16) * 257 for k in range(3))
            las.intensity = (rgb.astype(np.uint16).sum(axis=1) * 20).astype(np.uint16)
            las.return_number = np.ones(len(xyz), np.uint8)
            las.number_of_returns = np.ones(len(xyz), np.uint8)
            name = f"tile_{int(round(tx))}_{int(round(ty))}.laz"
            las.write(out / name)
            tiles.append(name)
            total += len(xyz)
    record = {"scene": str(scene), "seed": seed, "tile_m": tile_m, "tiles": tiles,
              "points": total, "line_spacing_m": 0.45, "point_spacing_m": 0.18,
              "grid": Grid.from_bounds(x0, y0, x1, y1, grid.gsd).shape}  # fmt: skip
    (out / "lidar.json").write_text(json.dumps(record, indent=1) + "\n")
    return record


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path, help="a sample scene folder (its truth/ is scanned)")
    ap.add_argument("out", type=Path, help="the folder of the LAZ tiles")
    ap.add_argument("--tile", type=float, default=250.0, help="tile side, metres")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rec = write_lidar_tiles(args.scene, args.out, args.tile, args.seed)
    print(f"{args.out}: {rec['points']:,} returns in {len(rec['tiles'])} tiles")


if __name__ == "__main__":
    main()

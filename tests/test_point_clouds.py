"""LiDAR as surveys deliver it: tiles in a projected CRS far from its origin, scan lines,
voids; and the super-pixel path on a terraced block from those tiles."""

import json

import laspy
import numpy as np
import pytest
from pyproj import CRS

from data_samples.terrace import scan_lines, write_terrace
from fusion.point_clouds import read_clouds
from fusion.points import default_gsd
from tests.conftest import SHARED_DATA, interrupted_after, run_cli
from workbench.errors import InputError
from workbench.raster import read_raster

ORIGIN = (500000.0, 5700000.0)  # UTM 31N, as a Dutch or Belgian survey would be


@pytest.fixture(scope="module")
def terrace(tmp_path_factory):
    out = tmp_path_factory.mktemp("terrace")
    write_terrace(out, seed=0, origin=ORIGIN, crs="EPSG:32631", tiles=2)
    return out


def _write_las(path, xyz, crs=None, cls=None):
    header = laspy.LasHeader(point_format=1, version="1.4")
    header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else [0.0, 0.0, 0.0]
    header.scales = [0.001] * 3
    if crs is not None:
        header.add_crs(CRS.from_user_input(crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    if cls is not None:
        las.classification = cls
    las.write(path)


def test_tiles_merge_into_the_cloud_they_were_cut_from(terrace, tmp_path):
    tiles = sorted((terrace / "tiles").glob("*.laz"))
    merged = read_clouds(tiles)
    assert merged.crs.to_epsg() == 32631  # laspy's parser read the header's WKT
    parts = [laspy.read(t) for t in tiles]
    assert len(merged.xyz) == sum(len(p.points) for p in parts)
    np.testing.assert_array_equal(
        merged.classification, np.concatenate([p.classification for p in parts])
    )
    assert merged.xyz[:, 0].min() > ORIGIN[0] - 20  # real coordinates, kept in float64
    # a folder is its tiles, and fusing them equals fusing one file holding them all
    whole = np.concatenate([np.column_stack([p.x, p.y, p.z]) for p in parts])
    _write_las(tmp_path / "whole.laz", whole, "EPSG:32631",
               np.concatenate([p.classification for p in parts]))  # fmt: skip
    for name, given in (("tiles", [terrace / "tiles"]), ("whole", [tmp_path / "whole.laz"])):
        proc = run_cli("fusion", "--points", *given, "-o", tmp_path / name, "--gsd", "0.5")
        assert proc.returncode == 0, proc.stderr
    a, grid_a, crs = read_raster(tmp_path / "tiles" / "dsm.tif")
    b, grid_b, _ = read_raster(tmp_path / "whole" / "dsm.tif")
    assert grid_a == grid_b and crs.to_epsg() == 32631
    np.testing.assert_allclose(a, b, atol=1e-6, equal_nan=True)
    record = json.loads((tmp_path / "tiles" / "fusion.json").read_text())
    assert [p.rsplit("/", 1)[1] for p in record["inputs"]["points"]] == [t.name for t in tiles]


def test_a_crs_in_an_extended_vlr_is_read(tmp_path):
    # LAS 1.4 may carry its WKT in an EVLR, after the points, with no VLR at all
    from laspy.vlrs.known import WktCoordinateSystemVlr
    from laspy.vlrs.vlrlist import VLRList

    las = laspy.LasData(laspy.LasHeader(point_format=6, version="1.4"))
    las.x, las.y, las.z = np.arange(10.0) + ORIGIN[0], np.arange(10.0) + ORIGIN[1], np.zeros(10)
    las.evlrs = VLRList([WktCoordinateSystemVlr(CRS.from_epsg(32631).to_wkt())])
    las.write(tmp_path / "evlr.laz")
    assert len(laspy.read(tmp_path / "evlr.laz").header.vlrs) == 0
    assert read_clouds([tmp_path / "evlr.laz"]).crs.to_epsg() == 32631


def test_tiles_of_different_crs_are_refused(tmp_path):
    xyz = np.random.default_rng(0).uniform(0, 50, (300, 3)) + [ORIGIN[0], ORIGIN[1], 0]
    _write_las(tmp_path / "a.laz", xyz, "EPSG:32631")
    _write_las(tmp_path / "b.laz", xyz, "EPSG:25831")
    proc = run_cli(
        "fusion", "--points", tmp_path / "a.laz", tmp_path / "b.laz", "-o", tmp_path / "o"
    )
    assert proc.returncode == 2 and not (tmp_path / "o").exists()
    line = proc.stderr.strip()
    assert len(line.splitlines()) == 1
    assert "b.laz" in line and "EPSG:25831" in line and "EPSG:32631" in line and "a.laz" in line


def test_empty_tiles_and_empty_folders_are_one_line_errors(tmp_path):
    _write_las(tmp_path / "empty.laz", np.zeros((0, 3)), "EPSG:32631")
    (tmp_path / "nothing").mkdir()
    for given, words in ((tmp_path / "empty.laz", "no points"),
                         (tmp_path / "nothing", "no .las, .laz or .ply file")):  # fmt: skip
        proc = run_cli("fusion", "--points", given, "-o", tmp_path / "o")
        assert proc.returncode == 2 and words in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1 and str(given) in proc.stderr
    with pytest.raises(InputError, match="empty.laz"):
        read_clouds([tmp_path / "empty.laz"])


def test_default_cell_holds_one_return_on_average_whatever_the_voids():
    rng = np.random.default_rng(0)
    xy = scan_lines((0.0, 0.0, 100.0, 100.0), rng, line_spacing=0.45, point_spacing=0.18)
    xyz = np.column_stack([xy, np.zeros(len(xy))])
    density = 1 / (0.45 * 0.18)  # 12.3 returns per m2
    assert default_gsd(xyz) == pytest.approx(np.sqrt(1 / density), rel=0.03)  # 0.28 m
    # a lake over a third of the tile (no returns) does not thin the density
    dry = xyz[xyz[:, 0] > 33.0]
    dry_with_corner = np.vstack([dry, [[0.0, 0.0, 0.0]]])  # the bounding box is unchanged
    assert default_gsd(dry_with_corner) == pytest.approx(np.sqrt(1 / density), rel=0.05)


def test_scan_line_stripes_are_filled_and_voids_stay_empty(terrace, tmp_path):
    truth_dsm, truth_grid, _ = read_raster(terrace / "truth" / "dsm.tif")
    # a pond of 6 m radius with no returns in the middle of the street
    tiles = sorted((terrace / "tiles").glob("*.laz"))
    las = [laspy.read(t) for t in tiles]
    xyz = np.concatenate([np.column_stack([p.x, p.y, p.z]) for p in las])
    cls = np.concatenate([p.classification for p in las])
    pond = np.hypot(xyz[:, 0] - (ORIGIN[0] + 40), xyz[:, 1] - (ORIGIN[1] - 19)) < 6.0
    _write_las(tmp_path / "pond.laz", xyz[~pond], "EPSG:32631", cls[~pond])
    # at the nearest-return spacing, a third of the cells hold no return
    proc = run_cli(
        "fusion", "--points", tmp_path / "pond.laz", "-o", tmp_path / "f", "--gsd", "0.27"
    )
    assert proc.returncode == 0, proc.stderr
    dsm, grid, _ = read_raster(tmp_path / "f" / "dsm.tif")
    count = read_raster(tmp_path / "f" / "count.tif")[0][0]
    assert (count == 0).mean() < 0.02 and (count == -1).mean() > 0.2  # filled, and marked
    X, Y = grid.cell_centers()
    in_pond = np.hypot(X - (ORIGIN[0] + 40), Y - (ORIGIN[1] - 19)) < 6.0 - 2 * 0.27 - 0.3
    assert np.isnan(dsm[0][in_pond]).all() and (count[in_pond] == 0).all()
    # filled cells sit on the true surface as the cells with returns do (off the walls)
    r, c = truth_grid.cell_index(X, Y, clip=True)
    err = dsm[0] - truth_dsm[0][r, c]
    walls = np.abs(np.gradient(truth_dsm[0], axis=(0, 1))).max(axis=0)[r, c] > 0.5
    filled, seen = (count == -1) & ~walls, (count > 0) & ~walls
    assert np.nanmedian(np.abs(err[filled])) < 0.05
    assert np.nanmedian(np.abs(err[filled])) < 1.5 * np.nanmedian(np.abs(err[seen]))


def test_terraced_block_from_tiles_is_one_region_modelled_on_its_planes(terrace, tmp_path):
    fusion, model, report = tmp_path / "f", tmp_path / "m", tmp_path / "r"
    proc = run_cli("fusion", "--points", terrace / "tiles", "-o", fusion)  # the default cell
    assert proc.returncode == 0, proc.stderr
    proc = run_cli("model", "superpixel", fusion, "-o", model, "--workers", "1")
    assert proc.returncode == 0, proc.stderr
    record = json.loads((model / "model.json").read_text())
    region = record["buildings"][0]
    # the terrace is one connected region of ~30,000 cells and thousands of super-pixels
    assert region["superpixels"] > 3000 and region["hypotheses"] > 500
    assert region["prototypes"] < region["hypotheses"]
    assert record["crs"] == "EPSG:32631"
    proc = run_cli("compare", model, "--truth", terrace / "truth", "-o", report, "--names", "model")
    assert proc.returncode == 0, proc.stderr
    m = json.loads((report / "metrics.json").read_text())["runs"]["model"]
    assert m["footprint_2d"]["quality"] > 0.96  # 0.981 measured
    assert m["height"]["rmse_off_jumps_m"] < 1.0  # 0.77 m measured


# -- unclassified returns: Autzen, where trees and the footbridge are all ASPRS 1 ----------

AUTZEN = SHARED_DATA / "autzen" / "autzen_trim.las"
# Drawn by hand on the fused ortho and nDSM of autzen_trim.las (1.9 ft cells, a 100 ft
# grid over them), in its CRS (Oregon State Plane South, US survey feet): eight single
# crowns as discs (centre x, y, radius), the row of cottonwoods on the river bank as a box,
# and the footbridge's deck as a 16 ft band along its axis.
CROWNS = [(636380, 849150, 18), (636407, 849112, 14), (636478, 849145, 20),
          (636780, 849165, 18), (636917, 849081, 20), (636970, 849115, 18),
          (636845, 849058, 14), (637000, 849040, 14)]  # fmt: skip
RIVER_BANK_TREES = (636100, 849285, 636330, 849360)
FOOTBRIDGE = ((636442, 849230), (636527, 849442))


@pytest.mark.skipif(not AUTZEN.exists(), reason="../shared/data is absent")
def test_unclassified_trees_are_trees_and_the_footbridge_is_not(tmp_path):
    import shapely
    from shapely.geometry import LineString, Point, box

    proc = run_cli("fusion", "--points", AUTZEN, "-o", tmp_path / "a")
    assert proc.returncode == 0, proc.stderr
    record = json.loads((tmp_path / "a" / "fusion.json").read_text())
    assert "geometry and echoes" in record["class_source"]
    cls, grid, _ = read_raster(tmp_path / "a" / "class.tif")
    ndsm = read_raster(tmp_path / "a" / "ndsm.tif")[0][0] * 0.3048  # metres
    X, Y = grid.cell_centers()
    centres = shapely.points(X, Y)
    trees = shapely.union_all(
        [Point(x, y).buffer(r) for x, y, r in CROWNS] + [box(*RIVER_BANK_TREES)]
    )
    deck = LineString(FOOTBRIDGE).buffer(8)
    up = ndsm > 2.5
    tree_cells = up & shapely.contains(trees, centres)
    deck_cells = up & shapely.contains(deck, centres)
    assert tree_cells.sum() > 1000 and deck_cells.sum() > 150
    # the raster forest trained on the synthetic city's colours made 72 % of these tree
    # cells building (99 % on an AHN3 tile); geometry and echoes, measured: 99.6 % tree,
    # 0.3 % building; the deck, a plane returning single echoes, 99 % building
    assert (cls[0][tree_cells] == 3).mean() > 0.97
    assert (cls[0][tree_cells] == 4).mean() < 0.01
    assert (cls[0][deck_cells] == 4).mean() > 0.9


# -- a survey larger than memory: its tiles read once, rasterised block by block ----------


def _street(folder, classified: bool = True) -> list:
    """A 420 x 110 m street as three LAZ tiles in UTM: sloping ground, houses (ASPRS 6)
    up to 24 m wide and crowns (ASPRS 5), returns on scan lines; unclassified (ASPRS 1)
    when not ``classified``."""
    rng = np.random.default_rng(11)
    xy = scan_lines((0.0, 0.0, 420.0, 110.0), rng, line_spacing=0.8, point_spacing=0.5)
    z = 2.0 + 0.01 * xy[:, 0] + 0.3 * np.sin(xy[:, 1] / 20.0)
    cls = np.full(len(xy), 2, np.uint8)
    for k in range(24):
        x0, y0 = 10 + 17 * k, rng.uniform(10, 70)
        w, d = rng.uniform(8, 24, 2)
        inside = (np.abs(xy[:, 0] - x0) < w / 2) & (np.abs(xy[:, 1] - y0) < d / 2)
        z[inside] += rng.uniform(4, 12) + 0.3 * (xy[inside, 1] - y0)  # a shed roof
        cls[inside] = 6
        crown = np.hypot(xy[:, 0] - x0 - 4, xy[:, 1] - 92) < rng.uniform(2.5, 5)
        z[crown] += rng.uniform(5, 9) + rng.normal(0, 0.5, crown.sum())
        cls[crown] = 5
    z += rng.normal(0, 0.03, len(z))
    if not classified:
        cls[:] = 1
    xyz = np.column_stack([xy + ORIGIN, z])
    folder.mkdir(exist_ok=True)
    tiles = []
    for t, (a, b) in enumerate([(0, 150), (150, 300), (300, 421)]):
        sel = (xy[:, 0] >= a) & (xy[:, 0] < b)
        _write_las(folder / f"street_{t}.laz", xyz[sel], "EPSG:32631", cls[sel])
        tiles.append(folder / f"street_{t}.laz")
    return tiles


@pytest.mark.parametrize("classified", [True, False])
def test_a_survey_in_blocks_is_the_whole_grid_byte_for_byte(tmp_path, classified):
    """Blocks of 100 m with their 80 m margins (outer blocks of at most 260 m of the
    street's 420 m) give every raster of the whole grid's run, byte for byte: the DSM's
    triangulation (near each block's inside only) and hole filling, the DTM from the
    ground class (or, unclassified, the morphological filter), and the classes from the
    files (or the returns' geometry)."""
    tiles = _street(tmp_path, classified)
    whole, blocks = tmp_path / "whole", tmp_path / "new" / "blocks"  # a folder to make too
    # cells of 0.35 m: the DSM's triangulated margin (96 cells) is 34 m of the 80 m
    proc = run_cli("fusion", "--points", *tiles, "-o", whole, "--gsd", "0.35")
    assert proc.returncode == 0, proc.stderr
    workers = ("--workers", "2") if classified else ()  # and as tasks of two workers
    proc = run_cli("fusion", "--points", tmp_path, "-o", blocks, "--block", "100", *workers,
                   "--gsd", "0.35")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    record = json.loads((blocks / "fusion.json").read_text())
    assert record["blocks"]["count"] == 10 and "blocks" not in json.loads(
        (whole / "fusion.json").read_text())  # fmt: skip
    # the DSM read on the triangulation near each block's inside only, not its margins
    assert record["blocks"]["triangulated_per_cell"] < 0.7 * record["blocks"][
        "returns_read_per_return"]  # fmt: skip
    assert record["dtm_source"] == ("LAS ground class (2), interpolated" if classified
                                    else "progressive morphological filter")  # fmt: skip
    for name in ("dsm", "dtm", "ndsm", "ortho", "class", "class_prob", "count"):
        a, grid_a, _ = read_raster(whole / f"{name}.tif")
        b, grid_b, _ = read_raster(blocks / f"{name}.tif")
        assert grid_a == grid_b
        np.testing.assert_array_equal(a, b, err_msg=name)
    cls = read_raster(blocks / "class.tif")[0][0]
    assert (cls == 4).mean() > 0.05 and (cls == 3).mean() > 0.005  # houses and crowns
    assert not list(tmp_path.rglob(".points-scratch*"))


def test_the_blocks_follow_the_survey_density():
    """By default a survey of up to 3 million returns is rasterised whole; a denser or
    larger one in blocks whose margins hold about that many returns."""
    from fusion.cloud_survey import Survey
    from fusion.points import BLOCK_RETURNS, cloud_block_size
    from workbench.grid_blocks import block_layout
    from workbench.raster import Grid

    def survey(n, area):
        tile = SpilledTile(None, np.zeros(2), np.ones(2), n)
        return Survey([], [tile], None, (), 1.0, n, area, None, 0)

    from fusion.cloud_survey import SpilledTile
    from fusion.options import FusionOptions

    grid = Grid(0.0, 1000.0, 0.3, 3334, 3334)
    opts = FusionOptions()
    assert cloud_block_size(grid, survey(BLOCK_RETURNS, 1e6), opts) is None
    # 12 returns a m2: an outer block of 500 m holds 3 million returns, 340 m less its
    # margins; the 1000 m grid is cut in three blocks a side (not four)
    side = cloud_block_size(grid, survey(12_000_000, 1e6), opts)
    assert side == pytest.approx(1000.2 / 3 + 0.3)
    assert len(block_layout(grid, side, 80.0)) == 9
    assert cloud_block_size(grid, survey(12_000_000, 1e6), FusionOptions(block=250)) == 250
    feet = Survey([], [SpilledTile(None, np.zeros(2), np.ones(2), 10)], None, (), 0.3048, 10,
                  1.0, None, 0)  # fmt: skip
    assert cloud_block_size(grid, feet, FusionOptions(block=250)) == pytest.approx(250 / 0.3048)


def test_intensity_percentile_of_a_histogram_is_numpys():
    from fusion.cloud_survey import percentile_of_counts

    values = np.random.default_rng(2).integers(0, 3000, 10_001)
    counts = np.bincount(values, minlength=1 << 16)
    for q in (0.0, 50.0, 99.0, 99.9, 100.0):
        assert percentile_of_counts(counts, q) == pytest.approx(np.percentile(values, q))
    assert percentile_of_counts(np.zeros(4, np.int64), 99.0) == 0.0


def test_a_bad_tile_among_good_ones_leaves_nothing_behind(tmp_path):
    tiles = _street(tmp_path)
    (tmp_path / "street_1.laz").write_bytes(b"LASF" + b"\0" * 50)
    proc = run_cli("fusion", "--points", *tiles, "-o", tmp_path / "o", "--block", "100")
    assert proc.returncode == 2
    assert "street_1.laz" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == [t.name for t in tiles]


def test_an_interrupted_survey_resumes_with_only_its_unfinished_blocks(tmp_path, monkeypatch):
    """Ten blocks, each a task: stopped (Ctrl-C) at the fourth, the run leaves no output
    and keeps three blocks; started again with resume, it rasterises the seven others
    only, and its rasters are the run through's, byte for byte."""
    import fusion.points as fp
    from fusion.options import FusionOptions
    from fusion.run import run_fusion
    from workbench.engine import TaskStore, partial_folder

    tiles = _street(tmp_path / "tiles")
    opts = FusionOptions(block=100.0, workers=1)
    through, out = tmp_path / "through", tmp_path / "out"
    run_fusion(through, opts, points=tiles)
    real, calls = fp.block_products, []
    monkeypatch.setattr(fp, "block_products", interrupted_after(real, 3, calls))
    with pytest.raises(KeyboardInterrupt):
        run_fusion(out, opts, points=tiles)
    assert not out.exists() and TaskStore(partial_folder(out)).finished("blocks") == 3
    calls.clear()
    monkeypatch.setattr(fp, "block_products", lambda *a: calls.append(1) or real(*a))
    record = run_fusion(out, opts, points=tiles, resume=True)
    assert len(calls) == 7 and record["blocks"]["count"] == 10
    for name in ("dsm", "dtm", "ortho", "class_prob", "count"):
        np.testing.assert_array_equal(read_raster(out / f"{name}.tif")[0],
                                      read_raster(through / f"{name}.tif")[0])  # fmt: skip
    assert not partial_folder(out).exists()
    assert not list(tmp_path.glob(".points-scratch*"))


def test_a_full_disk_while_spilling_the_tiles_is_one_line(tmp_path, monkeypatch):
    import errno

    import fusion.cloud_survey as cs
    from fusion.options import FusionOptions
    from workbench.errors import WorkbenchError

    tiles = _street(tmp_path / "tiles")

    def full(path, _a):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(cs.np, "save", full)
    with pytest.raises(WorkbenchError, match="disk full while keeping the survey's returns"):
        cs.spilled_survey(tiles, FusionOptions(), None, tmp_path / "scratch")


def test_a_sample_city_scanned_as_lidar_tiles_fuses_to_its_truth(tiny_scene, tmp_path):
    """``python -m data_samples.lidar`` on the tiny city (64 m): 4 LAZ tiles of 40 m in the
    scene's CRS, ASPRS classes, the scan's density (one return per 0.45 x 0.18 m); fused
    as one survey and scored against the truth, measured 0.053 m DSM RMSE off the jumps
    and 0.978 of the cells in their class."""
    import subprocess
    import sys

    from workbench.raster import raster_header

    tiles = tmp_path / "tiles"
    proc = subprocess.run([sys.executable, "-m", "data_samples.lidar", str(tiny_scene),
                           str(tiles), "--tile", "40"], capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    record = json.loads((tiles / "lidar.json").read_text())
    assert len(record["tiles"]) == 4 and sorted(p.name for p in tiles.glob("*.laz")) == sorted(
        record["tiles"])  # fmt: skip
    assert record["points"] / 64.0**2 == pytest.approx(1 / (0.45 * 0.18), rel=0.03)
    crs = raster_header(tiny_scene / "truth" / "dsm.tif", "truth")[2]
    for name in record["tiles"]:
        las = laspy.read(tiles / name)
        assert CRS.from_user_input(las.header.parse_crs()) == CRS.from_wkt(crs.to_wkt())
        assert set(np.unique(las.classification)) <= {2, 3, 5, 6}
    proc = run_cli("fusion", "--points", tiles, "-o", tmp_path / "fused", "--truth", tiny_scene)
    assert proc.returncode == 0, proc.stderr
    quality = json.loads((tmp_path / "fused" / "fusion.json").read_text())["quality"]
    assert quality["dsm"]["rmse_off_jumps_m"] < 0.07
    assert quality["classification"]["overall_accuracy"] > 0.97

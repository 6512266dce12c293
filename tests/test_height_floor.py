"""The noise-free floors of benchmarks/height_floor.py: hand-made roofs and the tiny city."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from workbench.raster import Grid
from workbench.truth import Truth

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from height_floor import height_floor, outline_inside_floor, voxel_proxy_floor  # noqa: E402


def _box(fid, x0, y0, x1, y1):
    ring = [[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]
    geometry = {"type": "Polygon", "coordinates": [ring]}
    return {"type": "Feature", "id": fid, "properties": {}, "geometry": geometry}


def test_perfect_proxies_of_a_flat_and_a_gable_roof(tmp_path):
    grid = Grid(0.0, 40.0, 0.25, 160, 160)
    X, Y = grid.cell_centers()
    ids = np.zeros(grid.shape, np.int64)
    flat = (X > 2) & (X < 12) & (Y > 2) & (Y < 12)
    gable = (X > 16) & (X < 36) & (Y > 10) & (Y < 22)
    ids[flat], ids[gable] = 1, 2
    dtm = np.full(grid.shape, 100.0)
    above = np.zeros(grid.shape)
    above[flat] = 7.0
    above[gable] = 6.0 + 4.0 * (1 - np.abs(Y[gable] - 16.0) / 6.0)  # eaves 6 m, ridge 10 m
    surface = np.where(ids > 0, dtm + above, np.nan)
    truth = Truth(grid, None, dsm=dtm + above, dtm=dtm, building_ids=ids, building_surface=surface)
    features = [_box("1", 2, 2, 12, 12), _box("2", 16, 10, 36, 22)]
    path = tmp_path / "footprints.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))

    # c_e = 1 keeps one cluster: every 1 m column of the gable snaps to the mean of the
    # twelve column heights across it, 6 + 4 * (1 - 3 / 6) = 8 m; the flat roof is exact
    one = voxel_proxy_floor(truth, path, 1.0, cluster_error=1.0)
    ridge = np.percentile(above[gable], 99)
    gable_error = 100 * (8.0 - ridge) / ridge
    assert one["height_error_pct_median"] == pytest.approx(abs(gable_error) / 2, abs=1e-6)
    # a small c_e splits the slope into levels, and the top level nears the ridge
    many = voxel_proxy_floor(truth, path, 1.0, cluster_error=0.01)
    assert many["height_error_pct_median"] < one["height_error_pct_median"] / 3


def test_floors_of_the_tiny_city(tiny_scene):
    f = height_floor(tiny_scene, returns=5)
    assert f["walls_displaced"]["0"]["building_rmse_m"] == pytest.approx(0.0, abs=1e-3)
    assert f["median_of_returns"]["dsm_rmse_off_jumps_m"] < 0.05
    cells = f["cells"]
    assert 0.85 < cells["observed_by_a_depth_map"] <= cells["seen_by_a_view"] <= 1.0
    c_e = [p["cluster_error"] for p in f["voxel_proxies"]]
    assert c_e == [0.3, 0.05]


def test_outlines_inside_the_true_ones_by_hand():
    """A 10 m tower of 20 x 20 cells on flat ground: an outline one cell inside loses
    only the ring of 76 cells the height jumps cover; two cells inside, the next ring
    too, 68 of the 324 cells off the jumps, 10 m off each."""
    grid = Grid(0.0, 10.0, 0.25, 40, 40)
    ids = np.zeros(grid.shape, np.int64)
    ids[10:30, 10:30] = 1
    dtm = np.zeros(grid.shape)
    surface = np.where(ids > 0, 10.0, np.nan)
    truth = Truth(grid, None, dsm=np.where(ids > 0, 10.0, 0.0), dtm=dtm, building_ids=ids,
                  building_surface=surface)  # fmt: skip
    f = outline_inside_floor(truth, (0, 1, 2))
    assert f["0"]["rmse_m"] == 0.0
    assert f["0.25"]["rmse_off_jumps_m"] == 0.0
    assert f["0.25"]["rmse_m"] == pytest.approx(10 * np.sqrt(76 / 400))
    assert f["0.5"]["rmse_off_jumps_m"] == pytest.approx(10 * np.sqrt(68 / 324))


def test_dsm_floor_gross_share_on_a_hand_made_dsm(tmp_path):
    from dsm_floor import gross_share

    from workbench.raster import write_raster

    grid = Grid(0.0, 10.0, 0.5, 20, 20)
    truth = np.full(grid.shape, 10.0, np.float32)
    dsm = truth + np.float32(0.1)
    dsm[5, 5] += 3.0  # one gross cell among 399 off by 0.1 m
    dsm[0, :] = np.nan  # unseen cells are not scored
    (tmp_path / "scene" / "truth").mkdir(parents=True)
    (tmp_path / "fusion").mkdir()
    write_raster(tmp_path / "scene" / "truth" / "dsm.tif", truth, grid, None)
    write_raster(tmp_path / "fusion" / "dsm.tif", dsm, grid, None)
    got = gross_share(tmp_path / "fusion", tmp_path / "scene")
    assert got["gross_cells"] == pytest.approx(1 / 380)
    share = 3.1**2 / (3.1**2 + 379 * 0.01)
    assert got["gross_share_of_squared_error"] == pytest.approx(share, rel=1e-5)  # float32


def test_survey_edge_splits_the_error_between_buildings_inside_and_beyond_the_viewpoints():
    """Two flat 10 m x 10 m roofs, one inside the viewpoints' rectangle, one reaching past
    its east side; a model 1 m high on the second only: 0 m inside, 1 m beyond, and over
    both the square root of the second's share of the scored cells."""
    from survey_edge import beyond_viewpoints, edge_split

    grid = Grid(0.0, 40.0, 0.5, 80, 80)
    X, Y = grid.cell_centers()
    ids = np.zeros(grid.shape, np.int64)
    ids[(X > 5) & (X < 15) & (Y > 5) & (Y < 15)] = 1
    ids[(X > 25) & (X < 35) & (Y > 5) & (Y < 15)] = 2
    dtm = np.zeros(grid.shape)
    surface = np.where(ids > 0, 8.0, np.nan)
    truth = Truth(grid, None, dsm=np.where(ids > 0, 8.0, 0.0), dtm=dtm, building_ids=ids,
                  building_surface=surface)  # fmt: skip
    centres = np.array([[0.0, 0.0, 150.0], [30.0, 40.0, 150.0]])  # x 0..30: building 2 past it
    beyond = beyond_viewpoints(truth, centres)
    assert np.array_equal(beyond, ids == 2)
    model = np.where(ids == 2, 9.0, np.where(ids == 1, 8.0, 0.0))
    f = edge_split(truth, beyond, model)
    # each roof is 20 x 20 cells; the jumps take its outer ring: 18 x 18 scored each
    assert f["cells_inside"] == f["cells_beyond"] == 18 * 18
    assert f["inside_rmse_off_jumps_m"] == 0.0 and f["beyond_rmse_off_jumps_m"] == 1.0
    assert f["rmse_off_jumps_m"] == pytest.approx(np.sqrt(0.5))
    assert f["beyond_share_of_square"] == 1.0

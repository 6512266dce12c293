"""A modeling path in blocks: each segment modelled by exactly one block, whichever way
two blocks draw it; the parametric path in blocks models the tiny city's buildings once
each, as the whole grid does."""

from __future__ import annotations

import json

import numpy as np
import pytest

from modeling.shared.in_blocks import BlockRasters, SegmentClaims
from tests.conftest import interrupted_after, model_and_score, run_cli
from workbench.grid_blocks import block_layout, whole_grid_block
from workbench.meshio import read_ply
from workbench.model_run import SurfacePieces
from workbench.raster import Grid, RasterWindows, read_raster, write_raster


def _rect(shape, rows, cols, label, out=None):
    out = np.zeros(shape, np.int32) if out is None else out
    out[rows[0] : rows[1], cols[0] : cols[1]] = label
    return out


@pytest.mark.parametrize("kept_in", ["memory", "file"])
def test_each_segment_is_modelled_by_one_block_however_the_blocks_draw_it(kept_in, tmp_path):
    """Two blocks of 20 x 20 cells side by side, 8 cells of margin: block 0 is worked over
    columns 0-28, block 1 over 12-40. Each block draws the same buildings a cell apart.
    The segments' numbers are kept in memory, or in a file written block by block."""
    grid = Grid(0.0, 20.0, 1.0, 40, 20)
    b0, b1 = block_layout(grid, 20.0, 8.0)
    assert (b0.outer[1].start, b0.outer[1].stop, b1.outer[1].start) == (0, 28, 12)
    claims = SegmentClaims(grid, [b0, b1], tmp_path if kept_in == "file" else None)
    # block 0's segments, on its outer columns 0-28 (the whole grid's columns):
    # 1 straddles the inner edge, its centre 19.5 in block 0;
    # 2 has its centre at 20.5, in block 1, and block 1 will draw it at 19.5;
    # 3 lies beyond block 0's cut edge (column 27), its centre in block 1;
    # 4 is wider than the margin: cut, its centre in block 0.
    s0 = _rect((20, 28), (1, 4), (15, 25), 1)
    _rect(None, (6, 9), (18, 24), 2, s0)
    _rect(None, (11, 14), (24, 28), 3, s0)
    _rect(None, (16, 19), (2, 28), 4, s0)
    todo, wide = claims.segments_to_model(b0, s0, 4, None, last=True)
    assert todo == [1, 4] and wide == 1
    assert list(claims.claim(b0, s0, 4, todo)) == [0, 1, 0, 0, 4]
    # block 1's, on its outer columns 12-40 (local column 0 is the whole grid's 12)
    s1 = _rect((20, 28), (1, 4), (16 - 12, 26 - 12), 1)
    _rect(None, (6, 9), (17 - 12, 23 - 12), 2, s1)
    _rect(None, (11, 14), (24 - 12, 30 - 12), 3, s1)
    _rect(None, (16, 19), (12 - 12, 38 - 12), 4, s1)
    todo, wide = claims.segments_to_model(b1, s1, 4, None, last=True)
    # 1: block 0 took 9 of its 10 cells; 2: its centre lies in block 0, which left it;
    # 3: whole here; 4: block 0 took most of it
    assert todo == [2, 3] and wide == 0
    # numbered on the whole grid: block 1's after block 0's four
    assert list(claims.claim(b1, s1, 4, todo)) == [0, 0, 6, 7, 0]
    assert claims.count == 4
    written = claims.ids.written()
    if kept_in == "file":
        assert claims.ids.file is not None and "rasters" not in written
        ids, on, _ = read_raster(written["raster_files"]["segments"])
        ids = ids[0]
        assert on == grid and ids.dtype == np.int32
    else:
        ids = written["rasters"]["segments"][0]
    assert set(np.unique(ids)) == {0, 1, 4, 6, 7}
    assert (ids[1:4, 15:25] == 1).all() and ids[1, 25] == 0  # block 1's extra cell left
    assert (ids[16:19, 2:28] == 4).all() and (ids[16:19, 28:38] == 0).all()


def test_before_the_last_round_a_block_runs_what_reaches_its_inner_cells():
    grid = Grid(0.0, 20.0, 1.0, 40, 20)
    b0, _ = block_layout(grid, 20.0, 8.0)
    claims = SegmentClaims(grid, block_layout(grid, 20.0, 8.0))
    s = _rect((20, 28), (1, 4), (2, 6), 1)
    _rect(None, (6, 9), (22, 26), 2, s)  # in the margin, its box not reaching column 20
    _rect(None, (11, 14), (22, 28), 3, s)  # cut by the edge
    boxes = np.array([[0, 0, 0, 0], [1, 4, 2, 6], [6, 9, 21, 27], [11, 14, 18, 28]])
    assert claims.segments_to_model(b0, s, 3, boxes, last=False) == ([1], 0)
    boxes[2, 2] = 19  # grown to reach the inner cells: its prior pulls the next round
    assert claims.segments_to_model(b0, s, 3, boxes, last=False) == ([1, 2], 0)


def test_block_rasters_join_the_ground_on_the_whole_grids_lattice(tmp_path):
    """Three blocks across a 40 x 90 cell grid (0.5 m cells, the ground's lattice every 4
    cells): the pieces' vertices are the whole grid's mesh's, each shared edge once per
    side; the preview's mosaic samples every 2nd cell; the DSM and DTM stay on disk; a
    path's own raster is written block by block into a file, each block's inner cells."""
    grid = Grid(0.0, 20.0, 0.5, 90, 40)
    blocks = block_layout(grid, 20.0, 4.0)
    assert [b.inner[1].start for b in blocks] == [0, 30, 60]
    rows, cols = np.indices(grid.shape)
    dtm = (rows * 0.1 + cols * 0.01).astype(np.float64)
    rgb = np.stack([rows, cols, rows + cols], axis=-1).astype(np.uint8)
    write_raster(tmp_path / "dtm.tif", dtm.astype(np.float32), grid, None)  # the fusion's
    (tmp_path / "store").mkdir()
    rasters = BlockRasters(grid, blocks, tmp_path, tmp_path / "store", preview_cells=45)
    numbers = (rows * 1000 + cols).astype(np.int32)
    for b in blocks:
        rasters.put(b, grid.window(*b.outer), dtm=dtm[b.outer], rgb=rgb[b.outer],
                    mask=(cols > 44)[b.outer])  # fmt: skip
        outer = np.full(numbers[b.outer].shape, -1, np.int32)  # the margins' cells: not
        outer[b.inside] = numbers[b.inner]  # written
        rasters.keep("numbers", b, outer, nodata=-2)
    whole = BlockRasters(grid, [whole_grid_block(grid)], tmp_path)
    whole.put(whole_grid_block(grid), grid, dtm=dtm, rgb=rgb)
    joined, one = rasters.ground(), whole.ground()
    assert isinstance(joined, SurfacePieces)  # on disk, for the writer to stream
    vertices = np.concatenate([v for v, _, _ in joined.pieces()])
    unique = np.unique(vertices, axis=0)
    assert np.array_equal(unique, np.unique(one.vertices, axis=0))
    assert joined.n_triangles == len(one.triangles)  # no gap, no overlap
    assert joined.n_vertices == len(vertices) == len(one.vertices) + 2 * 10  # two shared
    # columns of 10
    layers, coarse = rasters.preview_layers()
    mosaic, mask = layers["rgb"], layers["mask"]
    assert coarse.gsd == 1.0 and mosaic.shape == (20, 45, 3)
    assert np.array_equal(mosaic, rgb[::2, ::2]) and np.array_equal(mask, (cols > 44)[::2, ::2])
    files = rasters.model_rasters()
    assert files["dtm"] is None and files["raster_files"]["dtm"] == tmp_path / "dtm.tif"
    assert files["rasters"] == {} and files["raster_files"]["numbers"].parent == tmp_path / "store"
    written, on, _ = read_raster(files["raster_files"]["numbers"])
    assert on == grid and np.array_equal(written[0], numbers)


def test_raster_windows_read_what_the_whole_array_gives(tmp_path):
    grid = Grid(100.0, 200.0, 0.5, 30, 20)
    data = np.arange(600, dtype=np.float32).reshape(20, 30)
    data[3, 4] = np.nan
    write_raster(tmp_path / "dsm.tif", data, grid, None)
    r = RasterWindows(tmp_path / "dsm.tif", grid)
    assert r.shape == (20, 30)
    np.testing.assert_array_equal(r[2:9, 3:17], data[2:9, 3:17])


@pytest.mark.parametrize("path", ["parametric", "blocks", "superpixel"])
def test_a_path_in_blocks_models_each_building_once(path, tiny_scene, tiny_fusion, tiny_models,
                                                     tmp_path):  # fmt: skip
    """The tiny city (64 m) in 4 blocks of 32 m with 12 m of margin, each block segmented
    on its own: every building modelled once, as the whole grid models them (6 of 6
    found; parametric 2D quality 0.909 whole, blocks 0.93); the path's own rasters put
    together from the blocks."""
    out, record, m = model_and_score(
        tmp_path, tiny_scene, path, tiny_fusion, "--block", 32, "--block-margin", 12,
        "--workers", "1",
    )  # fmt: skip
    blocks = record["segmentation"]["blocks"] if path == "parametric" else record["blocks"]
    whole_run = tiny_models(path)[0]
    assert blocks["count"] == 4 and blocks["margin_m"] == 12
    _, _, whole = tiny_models(path)
    objects = m["footprint_2d"]["objects"]
    assert objects["found"] == 6
    assert objects["model_buildings"] == whole["footprint_2d"]["objects"]["model_buildings"]
    assert m["footprint_2d"]["quality"] > whole["footprint_2d"]["quality"] - 0.02
    assert m["complexity"]["watertight_fraction"] == 1.0
    ids = [b["id"] for b in record["buildings"]]
    assert len(set(ids)) == len(ids)
    # the ground, written piece by piece: the whole grid's lattice, the pieces' shared rows
    # of vertices at one height each (no crack), the same heights where the DTM is known
    mine, theirs = (read_ply(d / "ground.ply")[0] for d in (out, whole_run))
    mine = np.unique(mine, axis=0)
    assert np.array_equal(np.unique(mine[:, :2], axis=0), np.unique(theirs[:, :2], axis=0))
    assert len(mine) == len(np.unique(theirs, axis=0))
    dtm, grid, _ = read_raster(tiny_fusion / "dtm.tif")
    known = np.isfinite(dtm[0][grid.cell_index(mine[:, 0], mine[:, 1])])  # 93 % of them
    same = {tuple(v) for v in theirs.tolist()}
    assert all(tuple(v) in same for v in mine[known].tolist()) and known.mean() > 0.9
    assert read_ply(out / "scene.ply")[1].shape[0] == sum(
        read_ply(out / f)[1].shape[0] for f in ["ground.ply", *(f"buildings/{i}.ply" for i in ids)]
    )
    if path == "parametric":  # the segments' numbers, written block by block
        mine, theirs = (read_raster(d / "segments.tif")[0][0] > 0 for d in (out, whole_run))
        assert (mine == theirs).mean() > 0.98
    if path == "superpixel":  # the classes and super-pixels, written block by block
        mine, theirs = (read_raster(d / "class.tif")[0][0] for d in (out, whole_run))
        assert mine.shape == theirs.shape and (mine == theirs).mean() > 0.97
        # numbered on the whole grid: each block's own, after the blocks before (measured:
        # 2569 against the whole grid's 2514, those the blocks' inner edges cut counted twice)
        n = len(np.unique(read_raster(out / "superpixels.tif")[0][0]))
        whole_n = tiny_models(path)[1]["superpixels"]
        assert whole_n < n < 1.05 * whole_n


def test_a_superpixel_run_in_blocks_learns_its_crf_once(tiny_scene, tiny_fusion, tmp_path):
    """--omega-class auto and --geometry-unary in 4 blocks: learned on the block whose
    inner cells the strokes cover most, then applied to every block; --truth is refused
    in one line (each block would score its own classes)."""
    strokes = read_raster(tiny_scene / "training" / "labels.tif")
    assert strokes[0].any()
    out = tmp_path / "auto"
    args = ("model", "superpixel", tiny_fusion, "--block", 32, "--block-margin", 12,
            "--workers", "1")  # fmt: skip
    proc = run_cli(*args, "-o", out, "--omega-class", "auto", "--geometry-unary")
    assert proc.returncode == 0, proc.stderr
    record = json.loads((out / "model.json").read_text())
    learned = record["learned_on_block"]
    assert 0 <= learned["index"] < 4 and learned["stroke_cells"] > 0
    choice = record["omega_class_choice"]
    assert choice["scores"][str(choice["omega"])] == max(choice["scores"].values())
    assert "used" in record["geometry"] and record["blocks"]["count"] == 4
    proc = run_cli(*args, "-o", tmp_path / "o", "--truth", tiny_scene)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "--truth: not with --block" in proc.stderr and not (tmp_path / "o").exists()


def test_the_lod_path_in_blocks_learns_once_and_models_each_building_once(
    tiny_scene, tiny_fusion, tmp_path
):
    """The LOD path on the tiny city with its training strokes, whole and in 4 blocks of
    32 m with 12 m of margin: the classifier and the ground and grass colours learned
    once from the whole grid's strokes give the same tree probability, cell for cell (the
    features of a block's outer cells are one grid's: 48 cells of margin against their
    16); each building modelled once, as many as the whole grid models; the labelling
    (each block's ground heights its own) nearly the same."""
    labels = tiny_scene / "training" / "labels.tif"
    runs = {}
    for name, extra in (("whole", ()), ("blocks", ("--block", 32, "--block-margin", 12))):
        runs[name] = model_and_score(tmp_path / name, tiny_scene, "lod", tiny_fusion,
                                     "--labels", labels, *extra)  # fmt: skip
    (whole_dir, whole, wm), (out, record, m) = runs["whole"], runs["blocks"]
    assert "blocks" not in whole and record["blocks"]["count"] == 4
    assert record["labelling"]["flat_colours"] == whole["labelling"]["flat_colours"]
    mine, theirs = (read_raster(d / "tree_probability.tif")[0][0] for d in (out, whole_dir))
    assert np.array_equal(mine, theirs)
    mine, theirs = (read_raster(d / "class.tif")[0][0] for d in (out, whole_dir))
    assert (mine == theirs).mean() > 0.99  # measured: all of them
    ids = [b["id"] for b in record["buildings"]]
    assert len(set(ids)) == len(ids) == len(whole["buildings"])
    objects = m["footprint_2d"]["objects"]
    assert objects["found"] == wm["footprint_2d"]["objects"]["found"]  # 6 of 6
    assert m["footprint_2d"]["quality"] == pytest.approx(wm["footprint_2d"]["quality"], abs=0.01)
    assert m["complexity"]["watertight_fraction"] == 1.0


def test_an_interrupted_lod_run_in_blocks_redoes_only_its_unfinished_buildings(
    tiny_scene, tiny_fusion, tmp_path, monkeypatch
):  # fmt: skip
    """The LOD path in 4 blocks, its buildings the tasks of an engine with a task store:
    interrupted (Ctrl-C) at the fourth building and resumed, it models only the buildings
    not finished, and gives the run through's buildings and classes; its own rasters
    were written block by block into the store's folder, not held whole."""
    import modeling.lod.path as lp
    from modeling.lod.options import LodOptions
    from workbench.engine import TaskStore, engine_for, partial_folder, run_signature
    from workbench.model_run import BuildingsOnDisk

    opts = LodOptions(block_m=32.0, block_margin_m=12.0, workers=1)
    through = lp.run_lod(tiny_fusion, opts)  # no store: in memory
    out = tmp_path / "lod"
    sig = run_signature(opts, {"fusion_dir": tiny_fusion, "labels": None})
    real, calls = lp.building_lod, []
    monkeypatch.setattr(lp, "building_lod", interrupted_after(real, 3, calls))
    with pytest.raises(KeyboardInterrupt), engine_for(out, sig, workers=1) as engine:
        lp.run_lod(tiny_fusion, opts, engine=engine)
    partial = partial_folder(out)
    kept = [TaskStore(d).finished("buildings") for d in sorted(partial.glob("block_*"))]
    assert sum(kept) == 3

    calls.clear()
    monkeypatch.setattr(lp, "building_lod", lambda *a: calls.append(1) or real(*a))
    with engine_for(out, sig, workers=1, resume=True) as engine:
        resumed = lp.run_lod(tiny_fusion, opts, engine=engine)
        assert isinstance(resumed.buildings, BuildingsOnDisk)
        buildings = list(resumed.buildings)
        files = resumed.raster_files
        assert {"class", "tree_probability"} <= set(files) and not resumed.rasters
        classes = read_raster(files["class"])[0][0]
    assert len(calls) == through.counts["candidates"] - 3
    assert [b.id for b in buildings] == [b.id for b in through.buildings]
    for a, b in zip(buildings, through.buildings, strict=True):
        np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    np.testing.assert_array_equal(classes, through.rasters["class"][0])

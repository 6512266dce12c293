"""The fusion in blocks (fusion/blocks.py): the layout, the windows written where they
belong, resume block by block, and the default's switch to blocks."""

from __future__ import annotations

import errno
import json
import logging

import numpy as np
import pytest
import rasterio

from fusion.blocks import block_layout, block_size
from fusion.ground import LARGEST_WINDOW_M
from fusion.options import FusionOptions
from fusion.outputs import CEILING, RASTERS
from fusion.run import run_fusion
from workbench.engine import partial_folder
from workbench.errors import WorkbenchError
from workbench.grid_blocks import AUTO_BLOCK_CELLS
from workbench.raster import Grid, WindowedRaster, read_raster, write_raster


def test_blocks_cut_the_grid_once_and_their_margins_stop_at_its_edges():
    grid = Grid(500.0, 2000.0, 0.5, width=1000, height=450)  # 500 m x 225 m
    blocks = block_layout(grid, block_m=200.0, margin_m=20.0)
    # 3 blocks across (500 / 200 up), 2 down (225 / 200 up), cut evenly
    assert len(blocks) == 6
    assert [b.inner[1] for b in blocks[:3]] == [slice(0, 333), slice(333, 667), slice(667, 1000)]
    assert [b.inner[0] for b in blocks[::3]] == [slice(0, 225), slice(225, 450)]
    cover = np.zeros(grid.shape, int)
    for b in blocks:
        cover[b.inner] += 1
    assert (cover == 1).all()
    middle = blocks[1]  # 40 cells of margin each side, clipped at the grid's edges
    assert middle.outer == (slice(0, 265), slice(293, 707))
    assert middle.inside == (slice(0, 225), slice(40, 374))


def test_the_default_fuses_blocks_only_beyond_4096_cells_a_side():
    opts = FusionOptions()
    assert block_size(Grid(0.0, 0.0, 0.4, 2500, 2500), opts) is None  # the city preset
    big = Grid(0.0, 0.0, 0.4, 10000, 10000)
    side = block_size(big, opts)
    margin = np.ceil(LARGEST_WINDOW_M / 0.4)
    assert side == pytest.approx((AUTO_BLOCK_CELLS - 2 * margin) * 0.4)
    assert block_size(big, FusionOptions(block=300.0)) == 300.0


def test_a_raster_written_by_windows_is_the_raster_written_whole(tmp_path):
    grid = Grid(10.0, 20.0, 0.5, width=300, height=200)
    data = np.random.default_rng(0).random((3, 200, 300)).astype(np.float32)
    data[:, 5:9, 7:11] = np.nan
    write_raster(tmp_path / "whole.tif", data, grid, None, descriptions=["a", "b", "c"])
    w = WindowedRaster(tmp_path / "windows.tif", grid, None, np.float32, 3,
                       descriptions=["a", "b", "c"])  # fmt: skip
    for rows, cols in ((slice(0, 120), slice(0, 300)), (slice(120, 200), slice(0, 170)),
                       (slice(120, 200), slice(170, 300))):  # fmt: skip
        w.write(data[:, rows, cols], rows, cols)
    w.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["whole.tif", "windows.tif"]
    a, ga, _ = read_raster(tmp_path / "whole.tif")
    b, gb, _ = read_raster(tmp_path / "windows.tif")
    np.testing.assert_array_equal(a, b)
    assert ga == gb
    with rasterio.open(tmp_path / "windows.tif") as src:
        assert src.descriptions == ("a", "b", "c") and src.overviews(1)
        assert src.profile["blockxsize"] == 256 and src.profile["compress"] == "deflate"


def test_a_disk_too_small_for_the_whole_grid_files_is_one_line(tmp_path, monkeypatch):
    import fusion.blocks as fb

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(fb.os, "posix_fallocate", full)
    with pytest.raises(WorkbenchError) as e:
        fb.GridFiles(tmp_path / "grid", Grid(0.0, 100.0, 0.5, 200, 200))
    assert "dsm.npy: disk full" in str(e.value) and "\n" not in str(e.value)
    assert not list((tmp_path / "grid").iterdir())


@pytest.mark.slow
def test_blocks_interrupted_and_resumed_give_the_whole_grids_rasters(
    tiny_scene, tiny_fusion, tmp_path, monkeypatch, caplog
):  # fmt: skip
    """Blocks of 32 m on the 64 m tiny city: four blocks whose margin (80 m) holds the
    whole grid, so with the same forest each block's inside is the whole grid's fusion
    there, byte for byte, wherever its window is written. The run is interrupted after
    two blocks and resumed."""
    import fusion.outputs as outputs

    out = tmp_path / "blocks"
    opts = FusionOptions(block=32.0, workers=1, classifier=tiny_fusion.parent / "forest.joblib")
    real_write = outputs.FusionWindows.__call__
    written = []

    def interrupted_at_the_third(self, block, products):
        if len(written) == 2:
            raise KeyboardInterrupt
        written.append(block.index)
        real_write(self, block, products)

    monkeypatch.setattr(outputs.FusionWindows, "__call__", interrupted_at_the_third)
    with pytest.raises(KeyboardInterrupt):
        run_fusion(out, opts, scene=tiny_scene)
    assert not out.exists() and partial_folder(out).exists()
    assert not list(tmp_path.glob(".*windows.tif*")) and not list(tmp_path.glob(".blocks.tmp*"))
    monkeypatch.setattr(outputs.FusionWindows, "__call__", real_write)
    with caplog.at_level(logging.INFO):
        record = run_fusion(out, opts, scene=tiny_scene, resume=True)
    # the third block had its products when the write was interrupted
    assert "block 1 finished before, kept" in caplog.text
    assert "block 3 finished before, kept" in caplog.text
    assert "block 4 finished before" not in caplog.text
    assert not partial_folder(out).exists()
    # each block's margin holds the whole grid of 256 x 256 cells
    assert record["blocks"] == {"count": 4, "side_m": 32.0, "margin_m": LARGEST_WINDOW_M,
                                "cells_fused_per_cell": 4.0,
                                "largest_block_cells": 256 * 256}  # fmt: skip
    assert json.loads((out / "fusion.json").read_text())["blocks"]["count"] == 4
    for name, *_ in RASTERS + (CEILING,):
        a, ga, _ = read_raster(out / name)
        b, gb, _ = read_raster(tiny_fusion / name)
        assert ga == gb, name
        np.testing.assert_array_equal(a, b, err_msg=name)
    assert (out / "preview.png").stat().st_size > 0

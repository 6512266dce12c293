"""The voxel path's ground in tiles on disk (modeling/voxel/ground_tiles.py and the
tiled ground its run writes)."""

import itertools

import numpy as np

import modeling.voxel.path as vp
from modeling.voxel.ground_texture import GroundTexture
from modeling.voxel.ground_tiles import CUT, HEIGHTS, PAINTED, GroundTiles, PaintedGround
from workbench.engine import TaskStore
from workbench.raster import Grid, read_raster


def _tiled(tmp_path, arrays: dict, grid: Grid, size: int) -> GroundTiles:
    """``arrays`` ({stage: whole array}) cut into the tiles of ``size`` on a shelf."""
    tiles = GroundTiles(grid, size, TaskStore(tmp_path / "shelf"))
    for k, (rows, cols) in enumerate(tiles.tiles):
        for stage, a in arrays.items():
            tiles.shelf.save(stage, str(k), a[rows, cols])
    return tiles


def _coloured(s) -> dict:
    """{vertex: its colour} of a surface."""
    return {tuple(v): tuple(c) for v, c in zip(s.vertices, s.vertex_colors, strict=True)}


def test_a_window_is_put_together_from_the_tiles_it_overlaps(tmp_path):
    """A 5 x 7 grid in tiles of 3 (rows 0-2, 3-4; columns 0-2, 3-5, 6): every window
    read from the tiles is the window of the whole array."""
    grid = Grid(0.0, 5.0, 1.0, 7, 5)
    whole = np.arange(35.0).reshape(5, 7)
    tiles = _tiled(tmp_path, {HEIGHTS: whole}, grid, 3)
    assert len(tiles.tiles) == 6
    # rows 2-3 x columns 2-6 touch every tile; tile 4 (rows 3-4, columns 3-5) gives its
    # first row's columns 0-2 to the window's second row, columns 1-3
    parts = {k: (t, w) for k, t, w in tiles.overlapping(slice(2, 4), slice(2, 7))}
    assert sorted(parts) == [0, 1, 2, 3, 4, 5]
    assert parts[4] == ((slice(0, 1), slice(0, 3)), (slice(1, 2), slice(1, 4)))
    for r0, r1 in itertools.combinations(range(6), 2):
        for c0, c1 in itertools.combinations(range(8), 2):
            window = slice(r0, r1), slice(c0, c1)
            np.testing.assert_array_equal(tiles.read(HEIGHTS, *window), whole[window])


def test_painting_through_two_held_tiles_is_painting_the_whole_texture(tmp_path):
    """Windows painted one after another, overlapping and across tiles, with two tiles of
    nine held (the others saved on the shelf as they are let go): the texture read back
    is the whole texture painted the same way."""
    grid = Grid(0.0, 24.0, 1.0, 24, 24)
    rng = np.random.default_rng(0)
    whole = rng.integers(0, 255, (24, 24, 3), dtype=np.uint8)
    tiles = _tiled(tmp_path, {CUT: whole}, grid, 8)
    tiles.shelf.save(PAINTED, "3", np.zeros((8, 8, 3), np.uint8))  # a killed run's
    painted = PaintedGround(tiles, cached=2)
    assert tiles.shelf.finished(PAINTED) == 0  # a resumed run paints from the cuts
    for _ in range(40):
        r0, c0 = rng.integers(0, 20, 2)
        h, w = rng.integers(1, 12, 2)
        window = slice(r0, min(r0 + h, 24)), slice(c0, min(c0 + w, 24))
        image = painted.read(*window)
        np.testing.assert_array_equal(image, whole[window])
        image[rng.random(image.shape[:2]) < 0.5] = rng.integers(0, 255, 3, dtype=np.uint8)
        painted.paint(*window, image)
        whole[window] = image
    assert tiles.shelf.finished(PAINTED) > 0
    everything = slice(0, 24), slice(0, 24)
    np.testing.assert_array_equal(painted.read(*everything), whole)


def test_the_tiled_ground_is_the_whole_grounds_mesh_texture_and_heights(tmp_path, monkeypatch):
    """A 44 x 60 texel ground at 0.5 m (quads of 8 texels) in tiles of 16: the tiles'
    meshes have the whole mesh's vertices, with the same colours, and as many triangles,
    none twice; the heights written a tile at a time are the whole heights; the preview's
    mosaic is every third texel of the whole texture."""
    monkeypatch.setattr(vp, "PREVIEW_TEXELS", 20)
    grid = Grid(1000.0, 2000.0, 0.5, 60, 44)
    X, Y = grid.cell_centers()
    z = 10.0 + 0.05 * (X - 1000.0) + 0.02 * (2000.0 - Y) ** 1.5
    image = np.random.default_rng(1).integers(0, 255, (44, 60, 3), dtype=np.uint8)
    tiles = _tiled(tmp_path, {HEIGHTS: z, CUT: image}, grid, 16)
    (tmp_path / "out").mkdir()
    ground = vp.textured_ground(tiles, PaintedGround(tiles), {}, tmp_path / "out", None)
    whole = vp.ground_surface(GroundTexture(grid, z, image))
    pieces = list(ground.surface)
    assert len(pieces) == 12 and all(p.texture is not None for p in pieces)
    mine = {v: c for p in pieces for v, c in _coloured(p).items()}
    assert mine == _coloured(whole)
    assert sum(len(p.triangles) for p in pieces) == len(whole.triangles)
    corners = {frozenset(map(tuple, p.vertices[t])) for p in pieces for t in p.triangles}
    assert len(corners) == len(whole.triangles)  # no triangle twice
    dtm, _, _ = read_raster(ground.dtm_file)
    np.testing.assert_array_equal(dtm[0], z.astype(np.float32))
    np.testing.assert_array_equal(ground.image, image[::3, ::3])

"""A surface mesh from the views (`workbench mesh`, TSDF) and its orthogonal grid sampling
(`workbench fusion --mesh`): hand-computed planes, a texture, the tiny city against its
truth, a modeling path run from it, and bad meshes refused in one line."""

import dataclasses
import json

import numpy as np
import pytest

from fusion.mesh_sampling import SurfaceMesh, orthogonal_sampling, read_surface_mesh
from fusion.scene_mesh import (
    fitting_tile_m,
    grid_bytes,
    in_bounds,
    integrate_views,
    largest_tile_m,
    mesh_tiles,
    welded,
)
from tests.conftest import interrupted_after, run_cli
from workbench.errors import WorkbenchError
from workbench.imageio import write_rgb
from workbench.meshio import write_mtl, write_obj, write_ply
from workbench.raster import Grid, read_raster
from workbench.scene import load_scene


def slope_mesh(colors=True) -> SurfaceMesh:
    """z = 0.5 x + 2 over [0, 10]², red at x = 0 to blue at x = 10; and a flat square at
    z = 1 beneath it, which no vertical ray reaches first."""
    V = np.array([[0, 0, 2], [10, 0, 7], [10, 10, 7], [0, 10, 2],
                  [0, 0, 1], [10, 0, 1], [10, 10, 1], [0, 10, 1]], float)  # fmt: skip
    T = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    C = np.array([[255, 0, 0], [0, 0, 255], [0, 0, 255], [255, 0, 0]] * 2, np.uint8)
    return SurfaceMesh(None, V, T, C if colors else None, None, [], None, None)


def test_one_vertical_ray_per_cell_gives_the_top_surface_its_colour_and_normal():
    grid = Grid(0.0, 10.0, 1.0, 10, 10)
    ortho, dsm, normal = orthogonal_sampling(slope_mesh(), grid)
    X, _ = grid.cell_centers()
    assert dsm == pytest.approx(0.5 * X + 2, abs=1e-4)  # the upper plane, not the lower
    n = np.array([-0.5, 0.0, 1.0]) / np.hypot(0.5, 1.0)
    assert normal.reshape(3, -1).T == pytest.approx(np.tile(n, (100, 1)), abs=1e-5)
    # colour interpolated along x: red 255 (1 - x / 10), blue 255 x / 10
    assert ortho[..., 0] == pytest.approx(255 * (1 - X / 10), abs=1)
    assert ortho[..., 2] == pytest.approx(255 * X / 10, abs=1)


def test_cells_beyond_the_mesh_are_nan():
    grid = Grid(-5.0, 10.0, 1.0, 15, 10)  # a third of the grid west of the mesh
    ortho, dsm, normal = orthogonal_sampling(slope_mesh(colors=False), grid)
    assert np.isnan(dsm[:, :5]).all() and np.isfinite(dsm[:, 5:]).all()
    assert np.isnan(normal[:, :, :5]).all() and (ortho[:, :5] == 0).all()
    assert (ortho[:, 5:] == 128).all()  # no colour: grey


def bumps_over_a_floor() -> SurfaceMesh:
    """A bumpy surface of small triangles (0.5 m) far from the CRS's zero (UTM-like),
    coloured at random, over a large triangle."""
    rng = np.random.default_rng(0)
    n = 41
    x, y = np.meshgrid(np.linspace(0, 20, n), np.linspace(0, 20, n))
    z = 5 + rng.uniform(0, 2, x.shape)
    V = np.column_stack([x.ravel() + 500_000.0, y.ravel() + 5_700_000.0, z.ravel()])
    i = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    T = np.vstack([np.column_stack([i, i + 1, i + n + 1]), np.column_stack([i, i + n + 1, i + n])])
    big = len(V) + np.array([[0, 1, 2]])
    V = np.vstack([V, [[499_990.0, 5_699_990.0, 1.0], [500_090.0, 5_699_990.0, 1.0],
                       [499_990.0, 5_700_090.0, 1.0]]])  # fmt: skip
    C = rng.integers(0, 256, (len(V), 3)).astype(np.uint8)
    return SurfaceMesh(None, V, np.vstack([T, big]), C, None, [], None, None)


BUMPS_GRID = Grid(499_995.0, 5_700_025.0, 0.3, 100, 100)  # the bumps and the floor around


def test_tiles_cast_against_their_own_triangles_give_the_whole_meshs_hits():
    # each tile's scene holds only what is over it, and every hit is the one the scene
    # of the whole mesh gives; tiles of 3 cells (0.9 m) have every bump's triangle
    # longer than their margin, tiles of 7 and 32 only the floor
    mesh = bumps_over_a_floor()
    whole = orthogonal_sampling(mesh, BUMPS_GRID, tile=1000)
    assert np.isfinite(whole[1]).all() and (whole[1] < 2).any() and (whole[1] > 5).any()
    for tile in (3, 7, 32):
        ortho, dsm, normal = orthogonal_sampling(mesh, BUMPS_GRID, tile=tile)
        # a ray right on an edge may take either triangle: the same point, to rounding
        np.testing.assert_allclose(dsm, whole[1], rtol=0, atol=1e-5)
        np.testing.assert_allclose(normal, whole[2], rtol=0, atol=1e-6)
        assert np.abs(ortho.astype(int) - whole[0]).max() <= 1
        assert (dsm == whole[1]).mean() > 0.999 and (normal == whole[2]).all(axis=0).mean() > 0.999


def test_a_ply_read_a_part_at_a_time_samples_as_the_mesh_in_memory(tmp_path, monkeypatch):
    """The bumps written as PLY and read a part at a time, the tiles' triangles kept in
    memory or spilt to disk at every chunk: the products of the mesh in memory, to the
    bit; the spilt lists are gone afterwards."""
    from fusion.mesh_sampling import open_surface_mesh
    from fusion.mesh_source import PlySurface

    mesh = bumps_over_a_floor()
    write_ply(tmp_path / "bumps.ply", mesh.vertices, mesh.triangles, vertex_colors=mesh.colors,
              comments=["crs EPSG:32631"])  # fmt: skip
    ply = open_surface_mesh(tmp_path / "bumps.ply")
    assert isinstance(ply, PlySurface) and ply.crs.to_epsg() == 32631
    assert ply.lo == pytest.approx(mesh.vertices.min(axis=0))
    memory = orthogonal_sampling(mesh, BUMPS_GRID, tile=7)
    for buffer in (None, 0):
        if buffer is not None:
            monkeypatch.setattr("fusion.mesh_sampling.BUCKET_BUFFER_BYTES", buffer)
        scratch = tmp_path / f"scratch{buffer}"
        scratch.mkdir()
        for a, b in zip(orthogonal_sampling(ply, BUMPS_GRID, tile=7, scratch=scratch), memory,
                        strict=True):  # fmt: skip
            np.testing.assert_array_equal(a, b)
        assert not list(scratch.iterdir())


def test_non_manifold_edges_by_hand():
    from fusion.mesh_sampling import non_manifold_edges

    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1.0]])
    book = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # three pages on the edge 0-1
    everywhere = (-9, -9, 9, 9)
    assert non_manifold_edges(book, V[book], everywhere) == (1, 7)  # of 7 edges, one in 3
    assert non_manifold_edges(book[:2], V[book[:2]], everywhere) == (0, 5)  # a surface
    # a tile counts the edges whose midpoint it holds: 0-1's is (0.5, 0), x >= 0.5 here
    assert non_manifold_edges(book, V[book], (0.5, -9, 9, 9)) == (1, 4)  # 0-1, 1-2, 1-3, 1-4
    assert non_manifold_edges(book, V[book], (-9, -9, 0.5, 9)) == (0, 3)


def test_a_textured_obj_gives_its_texture(tmp_path):
    texture = np.zeros((64, 64, 3), np.uint8)
    texture[:, :32] = (200, 30, 30)  # left half (u < 0.5) red
    texture[:, 32:] = (30, 30, 200)
    write_rgb(tmp_path / "t.png", texture)
    V = np.array([[0, 0, 5], [10, 0, 5], [10, 10, 5], [0, 10, 5]], float)
    T = np.array([[0, 1, 2], [0, 2, 3]])
    uvs = V[T][..., :2] / 10.0
    write_mtl(tmp_path / "m.mtl", {"roof": (255, 255, 255)}, {"roof": "t.png"})
    write_obj(tmp_path / "m.obj", V, T, material="roof", mtllib="m.mtl", uvs=uvs)
    mesh = read_surface_mesh(tmp_path / "m.obj")  # no CRS: read, with a warning
    assert mesh.uvs is not None
    ortho, dsm, _ = orthogonal_sampling(mesh, Grid(0.0, 10.0, 1.0, 10, 10))
    assert (ortho[:, :5] == (200, 30, 30)).all() and (ortho[:, 5:] == (30, 30, 200)).all()
    assert dsm == pytest.approx(np.full((10, 10), 5.0))


@pytest.fixture(scope="module")
def mesh_fusion(tiny_scene, tmp_path_factory):
    root = tmp_path_factory.mktemp("mesh")
    proc = run_cli("mesh", tiny_scene, "-o", root / "city.ply")
    assert proc.returncode == 0, proc.stderr
    out = root / "fusion"
    proc = run_cli("fusion", "--mesh", root / "city.ply", "-o", out, "--gsd", "0.25",
                   "--bounds", "-32", "-32", "32", "32", "--truth", tiny_scene)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return root, out, json.loads((out / "fusion.json").read_text())


def test_the_tiny_city_mesh_sampled_matches_the_truth(mesh_fusion, tiny_scene):
    root, out, record = mesh_fusion
    assert record["mode"] == "mesh" and record["inputs"]["colour"] == "vertex colours"
    q = record["quality"]
    # measured: 0.133 m off jumps, 90.3 % valid, classes 0.987, ortho MAE 9.0
    assert q["dsm"]["rmse_off_jumps_m"] < 0.2 and q["dsm"]["valid_fraction"] > 0.88
    assert q["classification"]["overall_accuracy"] > 0.93
    assert q["ortho_mae"]["mean"] < 12
    normal, grid, crs = read_raster(out / "normal.tif")
    dsm, dgrid, _ = read_raster(out / "dsm.tif")
    assert normal.shape == (3, grid.height, grid.width) and grid == dgrid
    assert crs is not None  # from the PLY's header comment
    length = np.linalg.norm(normal, axis=0)
    assert np.nanmax(np.abs(length - 1)) < 1e-4 and np.nanmin(normal[2]) >= 0
    true_class, tgrid, _ = read_raster(tiny_scene / "truth" / "class.tif")
    ground = true_class[0] == 1  # the same grid: the scene's bounds at its gsd
    assert tgrid == grid
    assert np.nanmedian(normal[2][ground]) > 0.99


def test_a_mesh_fused_in_blocks_is_written_window_by_window(mesh_fusion, tiny_scene):
    """--block 20 on the tiny city's 64 m: 16 blocks, each with its 80 m margin the whole
    grid, so each block's products are the whole grid's, written block by block, made
    by a local cluster of two worker processes."""
    root, whole, record = mesh_fusion
    out = root / "blocks"
    proc = run_cli("fusion", "--mesh", root / "city.ply", "-o", out, "--gsd", "0.25", "--bounds",
                   "-32", "-32", "32", "32", "--block", "20", "--workers", "2")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    blocks = json.loads((out / "fusion.json").read_text())
    assert blocks["blocks"]["count"] == 16
    for key in ("missed_cells", "filled_cells"):  # the blocks' insides, not their margins
        assert blocks[key] == record[key]
    for name in ("ortho", "dsm", "normal", "dtm", "ndsm", "class", "class_prob", "count"):
        a, grid, crs = read_raster(whole / f"{name}.tif")
        b, bgrid, bcrs = read_raster(out / f"{name}.tif")
        assert bgrid == grid and bcrs == crs
        np.testing.assert_array_equal(a, b, err_msg=name)
    assert blocks["engine"]["workers"] == 2  # a local cluster: the same rasters
    assert not list(root.glob(".mesh-scratch-*"))  # the samples' scratch removed
    assert not list(root.glob(".blocks.partial"))


def test_a_mesh_fused_in_blocks_resumes_with_its_samples(mesh_fusion, monkeypatch):
    """Sixteen blocks, each a task: stopped (Ctrl-C) at the fourth, the run leaves no
    output and keeps the mesh's samples and three blocks; started again with resume, it
    samples nothing again and makes the thirteen others only, and its rasters are the
    whole grid's, byte for byte."""
    import fusion.mesh_sampling as ms
    from fusion.options import FusionOptions
    from fusion.run import run_fusion
    from workbench.engine import TaskStore, partial_folder

    root, whole, _ = mesh_fusion
    out = root / "resumed"
    opts = FusionOptions(gsd=0.25, bounds=(-32.0, -32.0, 32.0, 32.0), block=20.0, workers=1)
    real, calls = ms.mesh_block_products, []
    monkeypatch.setattr(ms, "mesh_block_products", interrupted_after(real, 3, calls))
    with pytest.raises(KeyboardInterrupt):
        run_fusion(out, opts, mesh=root / "city.ply")
    store = TaskStore(partial_folder(out))
    assert not out.exists() and store.finished("blocks") == 3
    assert (store.folder / "samples" / "sampled").exists()
    calls.clear()
    monkeypatch.setattr(ms, "mesh_block_products", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(ms, "sampled_tiles", None)  # called, it would fail
    record = run_fusion(out, opts, mesh=root / "city.ply", resume=True)
    assert len(calls) == 13 and record["blocks"]["count"] == 16
    for name in ("ortho", "dsm", "normal", "dtm", "class_prob", "count"):
        a, b = read_raster(out / f"{name}.tif")[0], read_raster(whole / f"{name}.tif")[0]
        np.testing.assert_array_equal(a, b, err_msg=name)
    assert not partial_folder(out).exists() and not list(root.glob(".mesh-scratch-*"))


def test_a_path_runs_from_the_mesh_fusion(mesh_fusion, tiny_scene):
    root, out, _ = mesh_fusion
    proc = run_cli("model", "superpixel", out, "-o", root / "sp", "--workers", "1")
    assert proc.returncode == 0, proc.stderr
    report = root / "report"
    proc = run_cli("compare", root / "sp", "--truth", tiny_scene, "-o", report)
    assert proc.returncode == 0, proc.stderr
    m = json.loads((report / "metrics.json").read_text())["runs"]["sp"]
    assert m["footprint_2d"]["objects"]["found"] >= 5  # of the tiny city's 6
    assert m["footprint_2d"]["quality"] > 0.72  # measured 0.758 (0.92 from the views)


def _write(tmp_path, V, T):
    path = tmp_path / "bad.ply"
    write_ply(path, np.asarray(V, float), np.asarray(T, np.int64).reshape(-1, 3))
    return path


@pytest.mark.parametrize(
    "V, T, field",
    [
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [], "faces"),
        ([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]], [[0, 1, 2]], "vertices"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]],
         [[0, 1, 2], [1, 0, 3], [0, 1, 4]], "faces"),  # an edge of three triangles
    ],
)  # fmt: skip
def test_a_mesh_that_is_not_a_surface_is_one_line(tmp_path, V, T, field):
    path = _write(tmp_path, np.asarray(V, float) + [500_000, 5_700_000, 0], T)
    proc = run_cli("fusion", "--mesh", path, "-o", tmp_path / "out", "--crs", "EPSG:32631",
                   "--gsd", "0.1")  # fmt: skip
    assert proc.returncode == 2 and str(path) in proc.stderr and field in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def test_a_mesh_that_is_not_a_surface_in_blocks_is_one_line(tmp_path):
    """In blocks the sampling finds the non-manifold edges after its last tile, when the
    rasters' windows and the samples' scratch exist: they go, the error is one line."""
    V = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]]
    path = _write(tmp_path, np.asarray(V, float) + [500_000, 5_700_000, 0],
                  [[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # fmt: skip
    proc = run_cli("fusion", "--mesh", path, "-o", tmp_path / "out", "--crs", "EPSG:32631",
                   "--gsd", "0.1", "--block", "0.5")  # fmt: skip
    assert proc.returncode == 2 and str(path) in proc.stderr and "faces" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.ply"]  # nothing else left


def test_a_mesh_outside_its_crs_area_is_one_line(tmp_path):
    path = _write(tmp_path, slope_mesh().vertices, slope_mesh().triangles)  # x 0-10 m
    proc = run_cli("fusion", "--mesh", path, "-o", tmp_path / "out", "--crs", "EPSG:32631")
    assert proc.returncode == 2 and "area of use" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def test_too_fine_a_grid_for_the_mesh_is_refused(tmp_path):
    path = _write(tmp_path, slope_mesh().vertices + [500_000, 5_700_000, 0], slope_mesh().triangles)
    proc = run_cli("fusion", "--mesh", path, "-o", tmp_path / "out", "--crs", "EPSG:32631",
                   "--gsd", "0.00005")  # fmt: skip
    assert proc.returncode == 2 and "GiB" in proc.stderr and not (tmp_path / "out").exists()


def test_mesh_refuses_an_existing_file_and_a_view_without_depth(tiny_scene, tmp_path):
    (tmp_path / "m.ply").write_text("keep")
    proc = run_cli("mesh", tiny_scene, "-o", tmp_path / "m.ply")
    assert proc.returncode == 2 and "exists" in proc.stderr
    assert (tmp_path / "m.ply").read_text() == "keep"
    proc = run_cli("mesh", tiny_scene, "-o", tmp_path / "m.obj")
    assert proc.returncode == 2 and "PLY" in proc.stderr


def test_a_view_that_touches_no_voxel_block_adds_nothing(tiny_scene, tmp_path):
    """A view whose depth inside the area is one pixel by the image's border (an oblique
    view that grazes the area: small seed 0's v002_E over part of the scene) touches no
    voxel block; Open3D aborted the whole integration on it. It is skipped."""
    scene = load_scene(tiny_scene)
    v = scene.views[2]  # v000_E, whose second column sees the area from row 317
    depth = v.read_depth()
    one = np.full(depth.shape, np.nan, np.float32)
    one[-18, 1] = depth[-18, 1]
    assert in_bounds(np.nan_to_num(one), v.camera, scene.bounds)[-18, 1] > 0
    np.save(tmp_path / "one.npy", one)
    grazing = dataclasses.replace(v, id="grazing", depth_path=tmp_path / "one.npy")
    few = dataclasses.replace(scene, views=scene.views[5:7])
    alone = integrate_views(few)
    with_it = integrate_views(dataclasses.replace(few, views=[grazing, *few.views]))
    assert np.array_equal(with_it.vertices, alone.vertices)
    assert np.array_equal(with_it.triangles, alone.triangles)


def test_a_tiled_mesh_is_the_whole_grid_s_mesh(mesh_fusion, tiny_scene, tmp_path):
    """Nine tiles of 30 m (the last ones cut by the 64 m area; each grid a block wider
    each side), written one after another, give the mesh of one grid over the area: the
    same vertices (none doubled where tiles meet), colours and triangles, only in the
    tiles' order; the file is what the tiles give in memory."""
    root, _, _ = mesh_fusion
    proc = run_cli("mesh", tiny_scene, "-o", tmp_path / "tiled.ply", "--tile", "30")
    assert proc.returncode == 0, proc.stderr
    assert "9 tiles" in proc.stdout
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".partial")]
    whole, tiled = read_surface_mesh(root / "city.ply"), read_surface_mesh(tmp_path / "tiled.ply")
    assert len(tiled.vertices) == len(whole.vertices)
    assert not np.array_equal(tiled.triangles, whole.triangles)  # the tiles' order
    vertices, colours, triangles = welded(tiled.vertices, tiled.triangles, tiled.colors)
    assert np.array_equal(vertices, whole.vertices)
    assert np.array_equal(colours, whole.colors)
    assert np.array_equal(triangles, whole.triangles)
    memory = integrate_views(load_scene(tiny_scene), tile_m=30)
    assert np.array_equal(memory.vertices, tiled.vertices)
    assert np.array_equal(memory.triangles, tiled.triangles)


def test_an_interrupted_tiled_mesh_resumes_with_only_its_unfinished_tiles(
    tiny_scene, tmp_path, monkeypatch
):  # fmt: skip
    """Nine tiles of 30 m, each a task: stopped (Ctrl-C) at the fourth, the run leaves no
    mesh and keeps three tiles and the views' blocks; started again with resume, it
    meshes the six others only and writes the run through's file, byte for byte."""
    import fusion.scene_mesh as sm
    from workbench.engine import TaskStore, partial_folder

    scene = load_scene(tiny_scene)
    through = tmp_path / "through.ply"
    sm.write_views_mesh(through, scene, workers=1, tile_m=30)
    out = tmp_path / "mesh.ply"
    real, calls = sm.tile_mesh, []
    monkeypatch.setattr(sm, "tile_mesh", interrupted_after(real, 3, calls))
    with pytest.raises(KeyboardInterrupt):
        sm.write_views_mesh(out, scene, workers=1, tile_m=30)
    assert not out.exists()
    store = TaskStore(partial_folder(out))
    assert store.finished("tiles") == 3 and store.has("view_blocks", "all")
    with pytest.raises(WorkbenchError, match="parameters.tile_m: the interrupted run"):
        sm.write_views_mesh(out, scene, workers=1, tile_m=20, resume=True)  # other tiles
    calls.clear()
    monkeypatch.setattr(sm, "tile_mesh", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(sm, "view_blocks", lambda *a: pytest.fail("the views' blocks again"))
    record = sm.write_views_mesh(out, scene, workers=1, tile_m=30, resume=True)
    assert len(calls) == 6 and record["tiles"] == 9
    assert out.read_bytes() == through.read_bytes()
    assert not partial_folder(out).exists()


def test_mesh_tiles_by_hand():
    # 0.25 m voxels: blocks of 2 m; a 3 m tile rounds up to 4 m
    tiles = mesh_tiles((0.0, 0.0, 10.0, 7.0), 0.25, 3.0)
    cores = [core for core, _ in tiles]
    inf = float("inf")  # the outer tiles keep what the surface has past the bounds
    assert cores == [(-inf, -inf, 4, 4), (4, -inf, 8, 4), (8, -inf, inf, 4),
                     (-inf, 4, 4, inf), (4, 4, 8, inf), (8, 4, inf, inf)]  # fmt: skip
    assert tiles[0][1] == (-2, -2, 6, 6)  # a block of margin each side
    assert tiles[-1][1] == (6, 2, 12, 9)  # the far sides end a block past the bounds
    # the largest tile whose grid fits: its estimate is the limit
    side = fitting_tile_m(0.25, 2**30)
    assert grid_bytes((0, 0, side + 4, side + 4), 0.25) == pytest.approx(2**30)
    # by default no more blocks than Open3D was seen to extract: the 1 km² city at 0.4 m
    # in 16 tiles of 278.4 m (87 blocks of 3.2 m), the last row and column 164.8 m
    city = mesh_tiles((-500.0, -500.0, 500.0, 500.0), 0.4, largest_tile_m(0.4))
    assert len(city) == 16 and city[0][0][2] == pytest.approx(-500 + 278.4)


def test_tiles_are_made_to_hold_their_blocks():
    """Tiles sized by the estimate of blocks per column are made smaller where the views'
    blocks are denser: none holds more than the limit after (a city's held 113,000 of
    the 60,000 meant)."""
    from fusion.scene_mesh import (
        MeshPlan,
        block_keys,
        fitted_tiles,
        key_xy,
        tile_block_count,
        tile_box,
    )

    bounds = (0.0, 0.0, 64.0, 64.0)  # 0.25 m voxels: blocks of 2 m, 32 a side
    plan = MeshPlan(0.25, 4.0, bounds, np.zeros(3), mesh_tiles(bounds, 0.25, 32.0), 0, 1.0,
                    2**40, fit_tiles=True)  # fmt: skip
    x, y, z = np.meshgrid(np.arange(16), np.arange(16), np.arange(10), indexing="ij")
    dense = np.column_stack([x.ravel(), y.ravel(), z.ravel()])  # 2560 in one corner
    keys = np.sort(block_keys(np.concatenate([dense, [[20, 20, 0], [31, 31, 0]]])))
    xy = key_xy(keys)

    def most(tiles):
        return max(tile_block_count(tile_box(*t, plan.origin, 0.25, xy), xy) for t in tiles)

    assert len(plan.tiles) == 4 and most(plan.tiles) == 2560  # the corner, whole in one
    tiles = fitted_tiles(plan, keys, max_blocks=1000)
    assert most(tiles) <= 1000 and len(tiles) > 4
    assert fitted_tiles(plan, keys, max_blocks=10**6) == plan.tiles  # dense enough already


def _block_views(root, blocks: list, height: float = 10.0) -> list:
    """Nadir views at 60 m, every 10 m along x, of blocks (x0 < x <= x1, every y,
    ``height`` tall) on flat ground at 0 m: exact z-depth maps (a pixel's centre at its
    integer coordinates, as OpenCV has them) and grey images written under ``root``."""
    from workbench.camera import Camera
    from workbench.imageio import write_rgb
    from workbench.scene import View

    w = h = 400
    f, c = 400.0, (w - 1) / 2
    K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
    R = np.diag([1.0, -1.0, -1.0])  # looking down, image x east, image y south
    u = (np.arange(w) - c) / f
    zc = 60.0
    views = []
    xs = np.arange(min(b[0] for b in blocks) - 20, max(b[1] for b in blocks) + 21, 10.0)
    for i, X in enumerate(xs):
        depth = np.full(w, zc)  # z-depth: the nearest surface along each column's ray
        x_top = X + u * (zc - height)
        with np.errstate(divide="ignore"):
            for x0, x1 in blocks:
                on_roof = (x_top > x0) & (x_top <= x1)
                depth = np.where(on_roof, np.minimum(depth, zc - height), depth)
                for xw in (x0, x1):  # a wall's plane, met between the roof's and the ground's
                    t = (xw - X) / u
                    depth = np.where((t > zc - height) & (t < zc), np.minimum(depth, t), depth)
        np.save(root / f"d{i}.npy", np.repeat(depth[None, :], h, axis=0).astype(np.float32))
        write_rgb(root / f"i{i}.png", np.full((h, w, 3), 128, np.uint8))
        cam = Camera(K, R, -R @ np.array([X, 0.0, zc]), w, h)
        views.append(View(f"v{i}", root / f"i{i}.png", cam, root / f"d{i}.npy"))
    return views


def test_a_walls_mesh_stands_where_the_views_see_it(tmp_path):
    # Open3D reads a projected voxel's pixel by truncating the projection: every surface
    # came out half a pixel's footprint along the image's axes (here 0.0625 m at the
    # roofs), each block east of where it stands on both its walls. A wall's vertices
    # also depend on where it falls between the voxels' corners (0.25 m apart): five
    # blocks 6 m wide, their walls 0.05 m further on each time
    from rasterio.crs import CRS

    from workbench.scene import Scene

    blocks = [(0.3 + 10.05 * k, 6.3 + 10.05 * k) for k in range(5)]
    scene = Scene(tmp_path, CRS.from_epsg(32631), _block_views(tmp_path, blocks),
                  bounds=(-4.0, -3.0, 52.0, 3.0), gsd=0.25)  # fmt: skip
    V = integrate_views(scene).vertices
    walls = V[(V[:, 2] > 2) & (V[:, 2] < 8) & (np.abs(V[:, 1]) < 2)]
    west, east = [], []
    for x0, x1 in blocks:
        west.append(np.median(walls[np.abs(walls[:, 0] - x0) < 1, 0]) - x0)
        east.append(np.median(walls[np.abs(walls[:, 0] - x1) < 1, 0]) - x1)
    # measured: the west walls 0.006 m off on average, the east walls 0.002 m (before:
    # 0.065 and 0.077 m east), each within 0.04 m
    assert abs(np.mean(west)) < 0.02 and abs(np.mean(east)) < 0.02
    roof = V[V[:, 2] > 9]
    assert abs(np.median(roof[:, 2]) - 10.0) < 0.01


def test_welded_ignores_the_order_a_mesher_gave():
    """A closed box shuffled (vertices and triangles, each triangle turned): the same
    arrays once welded, and every triangle keeps its winding."""
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(2.0, 3.0, 5.0)
    V, T = np.asarray(box.vertices), np.asarray(box.triangles)
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(V))
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(perm))
    T2 = inverse[T][rng.permutation(len(T))]
    T2 = np.array([np.roll(t, k) for t, k in zip(T2, rng.integers(0, 3, len(T2)), strict=True)])
    V2 = V[perm]
    w1, _, t1 = welded(V, T)
    w2, _, t2 = welded(V2, T2)
    assert np.array_equal(w1, w2) and np.array_equal(t1, t2) and len(w1) == len(V)

    # winding: the same directed edges, by their ends' positions
    def directed(vertices, triangles):
        return {tuple(np.r_[vertices[a], vertices[b]].round(6))
                for t in triangles for a, b in zip(t, np.roll(t, -1), strict=True)}  # fmt: skip

    assert directed(V, T) == directed(w1, t1)


@pytest.mark.parametrize("colours", ["equal", "different"])
def test_vertices_at_one_position_take_one_order_whichever_the_mesher_gave(colours):
    """Two sheets touching at the origin, each with its own vertex there (as marching
    cubes gives where two sheets meet): given in either order, the same arrays; twins of
    one colour made one vertex, of two colours ordered by colour."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [-1, 0, 0], [0, -1, 0]], float)
    T = np.array([[0, 1, 2], [3, 4, 5]])
    C = np.full((6, 3), 100, np.uint8)
    if colours == "different":
        C[0] = 50  # the twin of the sheet at x, y >= 0 darker
    swap = np.array([3, 1, 2, 0, 4, 5])  # the twins' places exchanged
    w1, c1, t1 = welded(V, T, C)
    w2, c2, t2 = welded(V[swap], swap[T], C[swap])
    assert np.array_equal(w1, w2) and np.array_equal(c1, c2) and np.array_equal(t1, t2)
    # by position: (-1, 0, 0) 0, (0, -1, 0) 1, the twin(s) 2 (and 3), then (0, 1, 0)
    # and (1, 0, 0); of two colours the darker twin first
    if colours == "equal":
        assert len(w1) == 5 and t1.tolist() == [[0, 1, 2], [2, 4, 3]]
    else:
        assert len(w1) == 6 and t1.tolist() == [[0, 1, 3], [2, 5, 4]]


def test_a_triangle_of_twins_is_dropped_whichever_order_the_mesher_gave():
    """Three vertices at one position and of one colour, the corners of a triangle of no
    area beside a sheet's triangle through that point (as the city's mesh had twice, the
    only bytes by which its files from 1 and 2 workers differed): one vertex, the
    triangle gone, the same arrays in either order."""
    V = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    T = np.array([[0, 1, 2], [2, 3, 4]])
    C = np.full((5, 3), 100, np.uint8)
    w1, c1, t1 = welded(V, T, C)
    for perm in ([2, 0, 1, 3, 4], [1, 2, 0, 4, 3]):
        perm = np.array(perm)
        inverse = np.argsort(perm)
        w2, c2, t2 = welded(V[perm], inverse[T], C[perm])
        assert np.array_equal(w1, w2) and np.array_equal(c1, c2) and np.array_equal(t1, t2)
    assert w1.tolist() == [[0, 0, 0], [0, 1, 0], [1, 0, 0]] and t1.tolist() == [[0, 2, 1]]


def test_an_open3d_ply_is_read_a_part_at_a_time_as_open3d_reads_it(tmp_path):
    """A PLY as an MVS tool writes it (Open3D's: double positions and vertex normals,
    uchar colours, `vertex_indices` a list of uchar and uint): read a part at a time, it
    samples as Open3D's own reading of it does."""
    import open3d as o3d

    from fusion.mesh_sampling import open_surface_mesh, read_surface_mesh
    from fusion.mesh_source import PlySurface

    bumps = bumps_over_a_floor()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(bumps.vertices),
                                     o3d.utility.Vector3iVector(bumps.triangles))  # fmt: skip
    mesh.vertex_colors = o3d.utility.Vector3dVector(bumps.colors / 255.0)
    mesh.compute_vertex_normals()
    path = tmp_path / "mvs.ply"
    assert o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=False)
    ply = open_surface_mesh(path, crs="EPSG:32631")
    assert isinstance(ply, PlySurface) and {"nx", "red"} <= set(ply.vertex_dtype.names)
    whole = read_surface_mesh(path, crs="EPSG:32631")
    for a, b in zip(orthogonal_sampling(ply, BUMPS_GRID, tile=32),
                    orthogonal_sampling(whole, BUMPS_GRID, tile=32), strict=True):  # fmt: skip
        np.testing.assert_array_equal(a, b)


def test_a_ply_cut_short_is_one_line(tmp_path):
    path = _write(tmp_path, slope_mesh().vertices + [500_000, 5_700_000, 0], slope_mesh().triangles)
    path.write_bytes(path.read_bytes()[:-20])  # the last face and a half gone
    proc = run_cli("fusion", "--mesh", path, "-o", tmp_path / "out", "--crs", "EPSG:32631")
    assert proc.returncode == 2 and str(path) in proc.stderr and "truncated" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()

"""GeoTIFF and mesh I/O: round trips of rasters (transform, CRS, NaN nodata) and meshes."""

import numpy as np
import open3d as o3d
import pytest
import rasterio
from rasterio.crs import CRS

from workbench.errors import InputError
from workbench.meshio import (
    PlyWriter,
    read_obj,
    read_ply,
    texture_of,
    write_mtl,
    write_obj,
    write_obj_pieces,
    write_ply,
)
from workbench.raster import Grid, class_codes, decimated_cells, read_raster, write_raster


def test_grid_geometry():
    g = Grid.from_bounds(-10, -4, 10, 6, 0.5)
    assert g.shape == (20, 40)
    assert g.bounds == (-10, -4, 10, 6)
    X, Y = g.cell_centers()
    assert X[0, 0] == -9.75 and Y[0, 0] == 5.75  # north-west cell centre
    r, c = g.world_to_cell(X, Y)
    np.testing.assert_allclose(r, np.arange(20)[:, None] + 0 * X)
    np.testing.assert_allclose(c, np.arange(40)[None, :] + 0 * X)


def test_a_mosaic_put_together_window_by_window_is_every_fth_cell():
    """The grid's rows 5-16, in an array starting at the grid's row 3: of every fourth
    row, the grid's 8, 12 and 16 (the array's 5, 9 and 13), the decimated grid's rows
    2-4; and windows of every size and origin put together give ``[::f, ::f]``."""
    inside, at = decimated_cells(slice(5, 17), slice(0, 7), 4, (3, 0))
    assert inside == (slice(5, 14, 4), slice(0, 7, 4)) and at == (slice(2, 5), slice(0, 2))
    whole = np.arange(23 * 17).reshape(23, 17)
    for f, size in ((1, 5), (3, 4), (4, 8), (5, 7)):
        mosaic = np.full((-(-23 // f), -(-17 // f)), -1)
        for rows, cols in Grid(0.0, 23.0, 1.0, 17, 23).tiles(size):
            origin = (max(rows.start - 1, 0), max(cols.start - 2, 0))  # a margin around
            window = whole[origin[0] : rows.stop + 1, origin[1] : cols.stop + 2]
            inside, at = decimated_cells(rows, cols, f, origin)
            mosaic[at] = window[inside]
        np.testing.assert_array_equal(mosaic, whole[::f, ::f])


def test_the_window_of_a_box_is_the_cells_it_touches():
    g = Grid(100.0, 200.0, 2.0, 10, 8)  # x 100-120, y 184-200
    # x 103-107.5: columns 1-3; y 195-199: rows 0-2
    assert g.window_of((103.0, 195.0, 107.5, 199.0)) == (slice(0, 3), slice(1, 4))
    # a cell around, clipped at the grid's top
    assert g.window_of((103.0, 195.0, 107.5, 199.0), pad=1) == (slice(0, 4), slice(0, 5))
    # edges on cell edges touch no more cells
    assert g.window_of((104.0, 190.0, 108.0, 194.0)) == (slice(3, 5), slice(2, 4))
    # beyond the grid: none
    assert g.window_of((130.0, 190.0, 140.0, 194.0)) is None


def test_raster_roundtrip_keeps_grid_crs_and_nan(tmp_path):
    g = Grid.from_bounds(100, 200, 132, 232, 1.0)
    data = np.arange(32 * 32, dtype=np.float32).reshape(32, 32)
    data[3, 4] = np.nan
    crs = CRS.from_epsg(32631)
    write_raster(tmp_path / "a.tif", data, g, crs)
    back, g2, crs2 = read_raster(tmp_path / "a.tif")
    assert g2 == g and crs2 == crs
    np.testing.assert_array_equal(back[0], data)


def test_read_raster_missing_names_file(tmp_path):
    with pytest.raises(InputError, match="nope.tif"):
        read_raster(tmp_path / "nope.tif", field="dsm")


def test_ply_roundtrip_and_open3d_reads_it(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) + 1000.25
    t = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    cls = np.array([4, 4, 1, 2], np.uint8)
    bid = np.array([7, 7, 0, -1], np.int32)
    write_ply(tmp_path / "m.ply", v, t, face_properties={"class": cls, "building_id": bid})
    v2, t2, props = read_ply(tmp_path / "m.ply")
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_array_equal(props["class"], cls)
    np.testing.assert_array_equal(props["building_id"], bid)
    m = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    assert len(m.triangles) == 4
    np.testing.assert_allclose(np.asarray(m.vertices), v)


def test_a_ply_written_in_pieces_is_the_ply_written_at_once(tmp_path):
    """Two pieces, the second's triangles using a vertex of the first: the file
    write_ply writes of the whole, byte for byte; an error inside leaves nothing."""
    V = np.array([[500000.0, 5e6, 1], [500001, 5e6, 1], [500000, 5e6 + 1, 1], [500001, 5e6 + 1, 2]])
    C = np.arange(12, dtype=np.uint8).reshape(4, 3)
    T = np.array([[0, 1, 2], [1, 3, 2]])
    write_ply(tmp_path / "whole.ply", V, T, vertex_colors=C, comments=["crs EPSG:32631"])
    with PlyWriter(tmp_path / "pieces.ply", colours=True, comments=["crs EPSG:32631"]) as ply:
        assert ply.add_vertices(V[:3], C[:3]) == 0
        ply.add_triangles(T[:1])
        assert ply.add_vertices(V[3:], C[3:]) == 3
        ply.add_triangles(T[1:])
    assert (tmp_path / "pieces.ply").read_bytes() == (tmp_path / "whole.ply").read_bytes()
    with pytest.raises(RuntimeError), PlyWriter(tmp_path / "broken.ply", colours=False) as ply:
        ply.add_vertices(V)
        raise RuntimeError("interrupted")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pieces.ply", "whole.ply"]


def test_obj_roundtrip_keeps_utm_millimetres_and_texture(tmp_path):
    """Open3D's OBJ reader rounds to single precision (0.5 m at a northing of 5.7e6 m);
    ours keeps what write_obj wrote (millimetres), its uvs and its texture."""
    v = np.array([[500000.123, 5700000.456, 10.0], [500010.0, 5700000.456, 10.0],
                  [500010.0, 5700010.0, 12.5], [500000.123, 5700010.0, 12.5]])  # fmt: skip
    t = np.array([[0, 1, 2], [0, 2, 3]])
    uvs = np.random.default_rng(0).random((2, 3, 2))
    write_obj(tmp_path / "b.obj", v, t, uvs=uvs, material="m", mtllib="b.mtl")
    write_mtl(tmp_path / "b.mtl", {"m": (255, 255, 255)}, {"m": "b.png"})
    vertices, triangles, read_uvs = read_obj(tmp_path / "b.obj")
    np.testing.assert_allclose(vertices, v, atol=5e-4)
    np.testing.assert_array_equal(triangles, t)
    np.testing.assert_allclose(read_uvs, uvs, atol=1e-6)
    assert texture_of(tmp_path / "b.obj") == tmp_path / "b.png"
    plain = tmp_path / "plain.obj"
    write_obj(plain, v, t)
    assert read_obj(plain)[2] is None and texture_of(plain) is None


def test_obj_written_in_chunks_is_the_obj_written_at_once(tmp_path, monkeypatch):
    """A city's ground is written a few rows at a time: the same bytes, whatever the
    chunk, with colours, uvs and runs of materials that end inside a chunk."""
    import workbench.meshio as meshio

    rng = np.random.default_rng(0)
    v, t = rng.random((53, 3)) * 1000, rng.integers(0, 53, (41, 3))
    colours, uvs = rng.integers(0, 255, (53, 3)).astype(np.uint8), rng.random((41, 3, 2))
    cases = [{"vertex_colors": colours}, {"material": [("a", 10), ("b", 31)], "uvs": uvs}]
    for k, kw in enumerate(cases):
        write_obj(tmp_path / f"one{k}.obj", v, t, **kw)
        monkeypatch.setattr(meshio, "OBJ_CHUNK", 7)
        write_obj(tmp_path / f"chunks{k}.obj", v, t, **kw)
        monkeypatch.undo()
        one = (tmp_path / f"one{k}.obj").read_bytes()
        assert one == (tmp_path / f"chunks{k}.obj").read_bytes()
        assert one.count(b"\nv ") == 53 and one.count(b"\nf ") == 41
    # the texture coordinates given piece by piece (a scene's buildings, then its ground)
    write_obj_pieces(tmp_path / "pieces.obj", lambda: iter([(v, t, None)]), 41,
                     material=[("a", 10), ("b", 31)],
                     uvs=lambda: iter([uvs[:10], uvs[10:]]))  # fmt: skip
    assert (tmp_path / "pieces.obj").read_bytes() == (tmp_path / "one1.obj").read_bytes()


def test_cell_index_nearest_and_clipped():
    g = Grid.from_bounds(0, 0, 4, 2, 1.0)  # 2 rows x 4 columns
    r, c = g.cell_index(
        np.array([0.01, 3.99, 2.5, -0.5, 4.5]), np.array([1.99, 0.01, 1.0, 1.5, 0.5])
    )
    np.testing.assert_array_equal(r[:2], [0, 1])
    np.testing.assert_array_equal(c[:2], [0, 3])
    assert not g.contains(r, c)[3:].any() and g.contains(r, c)[:2].all()
    rc, cc = g.cell_index(np.array([-0.5, 4.5]), np.array([1.5, 0.5]), clip=True)
    np.testing.assert_array_equal(cc, [0, 3])


def _raster_with_nodata(path, data, nodata, mask=None):
    """A GeoTIFF as other tools write them: a nodata value, or a mask band."""
    g = Grid.from_bounds(0, 0, data.shape[1], data.shape[0], 1.0)
    with rasterio.open(
        path, "w", driver="GTiff", width=data.shape[1], height=data.shape[0], count=1,
        dtype=data.dtype, crs=CRS.from_epsg(32631), transform=g.transform, nodata=nodata,
    ) as dst:  # fmt: skip
        dst.write(data, 1)
        if mask is not None:
            dst.write_mask(np.where(mask, 0, 255).astype(np.uint8))
    return g


@pytest.mark.parametrize("nodata", [-9999.0, 0.0, np.nan])
def test_float_nodata_reads_as_nan(tmp_path, nodata):
    data = np.full((8, 8), 12.5, np.float32)
    data[2, 3] = data[5, 5] = nodata
    _raster_with_nodata(tmp_path / "a.tif", data, nodata)
    back = read_raster(tmp_path / "a.tif")[0][0]
    assert back.dtype == np.float32
    assert np.isnan(back[2, 3]) and np.isnan(back[5, 5]) and np.isfinite(back).sum() == 62
    assert (back[np.isfinite(back)] == 12.5).all()


def test_an_integer_dem_reads_as_heights_with_nan(tmp_path):
    data = np.full((8, 8), 42, np.int16)
    data[0, 0] = -32768
    _raster_with_nodata(tmp_path / "dem.tif", data, -32768)
    heights = read_raster(tmp_path / "dem.tif", as_float=True)[0][0]
    assert np.isnan(heights[0, 0]) and (heights[1:] == 42.0).all()
    classes = read_raster(tmp_path / "dem.tif")[0][0]  # as a class raster: 0 is no data
    assert classes.dtype == np.int16 and classes[0, 0] == 0 and (classes[1:] == 42).all()


def test_a_mask_band_is_nodata_too(tmp_path):
    data = np.full((8, 8), 3.0, np.float32)
    mask = np.zeros((8, 8), bool)
    mask[4, :] = True
    _raster_with_nodata(tmp_path / "m.tif", data, None, mask=mask)
    back = read_raster(tmp_path / "m.tif")[0][0]
    assert np.isnan(back[4]).all() and (back[~mask] == 3.0).all()


def test_rasters_are_cloud_optimized_with_fitting_overviews(tmp_path):
    grid = Grid(500000.0, 5700600.0, 0.25, 600, 600)  # UTM 31N
    heights = np.add.outer(np.arange(600.0), np.arange(600.0)).astype(np.float32)
    heights[:10] = np.nan
    classes = np.random.default_rng(0).choice([0, 1, 4], (600, 600)).astype(np.uint8)
    write_raster(tmp_path / "dsm.tif", heights, grid, CRS.from_epsg(32631))
    write_raster(tmp_path / "class.tif", classes, grid, CRS.from_epsg(32631), nodata=0)
    for name in ("dsm.tif", "class.tif"):
        with rasterio.open(tmp_path / name) as ds:
            assert ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
            assert ds.block_shapes[0] == (256, 256) and ds.overviews(1) == [2, 4]
    with rasterio.open(tmp_path / "dsm.tif", overview_level=0) as ds:
        half = ds.read(1)
    # heights average: a 2 x 2 block of the plane x + y averages to its centre
    assert half[100, 100] == pytest.approx(np.mean(heights[200:202, 200:202]))
    with rasterio.open(tmp_path / "class.tif", overview_level=0) as ds:
        assert set(np.unique(ds.read(1))) <= {0, 1, 4}  # classes are picked, never averaged
    data, g, _ = read_raster(tmp_path / "dsm.tif")
    assert g == grid and np.isnan(data[0, :10]).all()


@pytest.mark.parametrize("band", [1, 2, 256])
def test_class_codes_are_the_most_probable_class_and_0_unseen(band):
    prob = np.full((4, 3, 2), np.nan, np.float32)  # the first row's cells unseen
    prob[:, 1, 0] = [0.1, 0.2, 0.6, 0.1]  # tree
    prob[:, 1, 1] = [0.4, 0.4, 0.1, 0.1]  # a tie: the first, ground
    prob[:, 2, 0] = [0.2, np.nan, 0.1, 0.3]  # a class without confidence counts as 0
    prob[:, 2, 1] = [0.0, 0.0, 0.0, 1.0]
    codes = class_codes(prob, band=band)
    assert codes.dtype == np.uint8
    np.testing.assert_array_equal(codes, [[0, 0], [3, 1], [4, 4]])

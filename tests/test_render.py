"""Pictures of meshes: the models drawn in batches are the models drawn at once."""

import numpy as np
from shapely.geometry import box

from modeling.shared.roof_mesh import extrude_faces
from workbench import render
from workbench.model_run import Building, Surface, Texture


def _block(bid: str, x0: float, height: float, colour=None) -> Building:
    V, T = extrude_faces([box(x0, 0, x0 + 10, 6)], [np.array([0.0, 0.0, 1.0, -height])], 0.0)
    tex = None
    if colour is not None:  # a one-colour atlas
        tex = Texture(np.full((4, 4, 3), colour, np.uint8), np.full((len(T), 3, 2), 0.5))
    return Building(bid, Surface(V, T, texture=tex), "1.3")


def test_buildings_drawn_in_batches_are_drawn_as_at_once(monkeypatch):
    # the tall one, drawn first, stands in front of the low one: depth decides
    buildings = [_block("tall", 0.0, 20.0), _block("low", 8.0, 5.0), _block("far", 30.0, 9.0)]
    bounds = (-5.0, -5.0, 45.0, 15.0)
    at_once = render.render_buildings(buildings, bounds)
    monkeypatch.setattr(render, "RENDER_BATCH", 1)  # a batch per building
    batched = render.render_buildings(buildings, bounds)
    background = (at_once == render._BACKGROUND).all(axis=2)
    assert 0.05 < 1 - background.mean() < 0.9  # the buildings are in the picture
    assert np.mean(np.any(batched != at_once, axis=2)) < 1e-4  # ties at shared edges only
    assert render.render_buildings([], bounds) is None


def test_textured_buildings_drawn_in_batches_are_drawn_as_at_once(monkeypatch):
    from modeling.voxel.preview import render_textured

    colours = {"tall": (200, 0, 0), "low": (0, 200, 0), "far": (0, 0, 200)}
    # the far one, drawn last, stands behind the tall one from the south-west
    buildings = [_block("tall", 0.0, 20.0, colours["tall"]),
                 _block("low", 12.0, 5.0, colours["low"]),
                 _block("far", 26.0, 30.0, colours["far"])]  # fmt: skip
    at_once = render_textured(buildings)
    shown = {k: (at_once == c).all(axis=2).mean() for k, c in colours.items()}
    assert min(shown.values()) > 0.005, shown  # every building shows its atlas
    monkeypatch.setattr(render, "RENDER_BATCH", 1)  # a batch per building
    batched = render_textured(buildings)
    np.testing.assert_array_equal(batched, at_once)
    import modeling.voxel.preview as preview

    monkeypatch.setattr(render, "RENDER_BATCH", 10**9)
    monkeypatch.setattr(preview, "RENDER_IMAGE_BYTES", 1)  # a batch per atlas
    np.testing.assert_array_equal(render_textured(buildings), at_once)
    # depth decides, not the order: drawn the other way round, the same picture
    np.testing.assert_array_equal(render_textured(buildings[::-1]), at_once)


def test_a_batch_closes_at_its_triangles_or_its_images_bytes():
    """Parts of 3 triangles and a 6-byte image each: with 5 triangles a batch closes
    after 2 parts (6 triangles), with 12 bytes after 2 (12 bytes), with 13 after 3."""
    parts = [(None, np.zeros((3, 3)), None, np.zeros(6, np.uint8)) for _ in range(5)]
    assert [len(b) for b in render.triangle_batches(parts, limit=5)] == [2, 2, 1]
    by_bytes = render.triangle_batches(parts, limit=100, image_bytes=12)
    assert [len(b) for b in by_bytes] == [2, 2, 1]
    by_bytes = render.triangle_batches(parts, limit=100, image_bytes=13)
    assert [len(b) for b in by_bytes] == [3, 2]

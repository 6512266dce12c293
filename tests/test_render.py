"""Pictures of meshes: the models drawn in batches are the models drawn at once."""

import numpy as np
from shapely.geometry import box

from modeling.shared.roof_mesh import extrude_faces
from workbench import render
from workbench.model_run import Building, Surface


def _block(bid: str, x0: float, height: float) -> Building:
    V, T = extrude_faces([box(x0, 0, x0 + 10, 6)], [np.array([0.0, 0.0, 1.0, -height])], 0.0)
    return Building(bid, Surface(V, T), "1.3")


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

"""Ground and grass weighed by each cell's colour (fusion.flat_colours)."""

import numpy as np

from fusion.flat_colours import weigh_flat_classes
from workbench.ground_grass_colours import MIN_CELLS, fit_flat_colours, ground_factor

PAVING, LAWN = (150, 150, 145), (70, 120, 50)


def _training(n=400, seed=0):
    """Pixels of grey paving (ground), green lawn (grass) and a green crown (tree), with
    a few units of noise."""
    rng = np.random.default_rng(seed)
    rgb = np.concatenate([np.tile(PAVING, (n, 1)), np.tile(LAWN, (n, 1)), np.tile(LAWN, (n, 1))])
    rgb = np.clip(rgb + rng.normal(0, 4, rgb.shape), 0, 255).astype(np.uint8)
    labels = np.repeat([1, 2, 3], n)
    return rgb, labels


def test_a_paving_strip_the_forest_calls_grass_becomes_ground():
    model, record = fit_flat_colours(*_training(), seed=0)
    assert record["used"] and record["training_cells"] == {"ground": 400, "grass": 400}
    # a 3-cell row: paving, lawn, and a cell the forest is sure is a crown
    ortho = np.array([[PAVING, LAWN, LAWN]], np.uint8)
    prob = np.zeros((4, 1, 3), np.float32)
    prob[:, 0, 0] = (0.3, 0.7, 0.0, 0.0)  # the patch saw the lawn beside the paving
    prob[:, 0, 1] = (0.3, 0.7, 0.0, 0.0)
    prob[:, 0, 2] = (0.05, 0.05, 0.9, 0.0)
    weigh_flat_classes(prob, ortho, model)
    assert np.argmax(prob[:, 0, 0]) == 0  # ground
    assert np.argmax(prob[:, 0, 1]) == 1  # grass, more surely than before
    assert prob[1, 0, 1] > 0.7
    # tree keeps its share against the two flat classes: their factors sum to 2
    assert abs(prob[2, 0, 2] - 0.9) < 0.05
    np.testing.assert_allclose(prob.sum(axis=0), 1.0, atol=1e-6)
    f = ground_factor(model, ortho)
    assert f[0, 0] > 1.99 and f[0, 1] < 0.01


def test_unseen_cells_stay_unknown_and_too_few_pixels_fit_nothing():
    model, _ = fit_flat_colours(*_training(), seed=0)
    prob = np.full((4, 1, 1), np.nan, np.float32)
    weigh_flat_classes(prob, np.zeros((1, 1, 3), np.uint8), model)
    assert np.isnan(prob).all()
    rgb, labels = _training(n=MIN_CELLS - 1)
    model, record = fit_flat_colours(rgb, labels, seed=0)
    assert model is None and not record["used"] and "ground" in record["reason"]

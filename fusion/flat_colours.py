"""Ground and grass told apart by each cell's own colour (not in the super-pixel paper).

Both lie flat on the terrain, so only colour separates them, and the per-view forest
reads colour over an 11 x 11 patch: a strip of paving a metre wide between a wall and a
lawn looks like the lawn beside it, and its elevation statistics (the wall in the patch)
like no stroke the forest learnt ground from. On the tuning seeds 0-2 and 6-7, 92-95 % of
the ground cells classed grass lay within six cells of a building, and 10-31 % of those
aprons were grass. The ortho shows them sharply. So the ortho's colours under the
training strokes of each of the two classes are modelled as a Gaussian mixture in CIE
Lab, and each cell's ground and grass confidences are multiplied by the two likelihoods
of its ortho colour, normalised to sum to 2: the product of two experts, the patch's
forest and the cell's colour (Hinton 2002), with colour models as GrabCut's (Rother et
al. 2004; the models: :mod:`workbench.ground_grass_colours`). Tree and building keep
theirs.

The models are fitted to the ortho, the colours they weigh, not to the view pixels the
forest learns from: fitted to those, the same rule gained less on every tuning seed, and
on `tiny` it took a beige ground beside a building for grass (overall accuracy 0.976 ->
0.965, against 0.993 fitted to the ortho).
"""

from __future__ import annotations

import numpy as np

from workbench.ground_grass_colours import FlatColours, fit_flat_colours, ground_factor
from workbench.raster import GRASS, GROUND

from .classifier import CLASSES


def weigh_flat_classes(class_prob: np.ndarray, ortho: np.ndarray, model: FlatColours) -> None:
    """Multiply the ground and grass confidences of ``class_prob`` (4, H, W) float32,
    NaN where unseen, by the colour factors of ``ortho`` (H, W, 3) uint8 and renormalise
    each cell, in place."""
    f = ground_factor(model, ortho)
    class_prob[CLASSES.index(GROUND)] *= f
    class_prob[CLASSES.index(GRASS)] *= 2.0 - f
    with np.errstate(invalid="ignore", divide="ignore"):
        class_prob /= class_prob.sum(axis=0, keepdims=True)


def weigh_by_stroke_colours(class_prob: np.ndarray, ortho: np.ndarray, strokes: np.ndarray,
                            seed: int) -> dict:  # fmt: skip
    """Fit the colour models to the ortho under the training strokes and weigh the
    ground and grass confidences by them (:func:`weigh_flat_classes`), in place.

    Parameters
    ----------
    class_prob : (4, H, W) float32
        Class confidences, NaN where unseen.
    ortho : (H, W, 3) uint8
    strokes : (H, W) int
        Training labels 1-4 on the same grid, 0 where none.
    seed : int

    Returns
    -------
    the models' record for ``fusion.json`` (``used`` False, and why, when unfitted)
    """
    on = np.isfinite(class_prob[0]) & np.isin(strokes, (GROUND, GRASS))
    model, record = fit_flat_colours(ortho[on], np.asarray(strokes)[on], seed)
    if model is not None:
        weigh_flat_classes(class_prob, ortho, model)
    return record

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
al. 2004). Tree and building keep theirs.

The models are fitted to the ortho, the colours they weigh, not to the view pixels the
forest learns from: fitted to those, the same rule gained less on every tuning seed, and
on `tiny` it took a beige ground beside a building for grass (overall accuracy 0.976 ->
0.965, against 0.993 fitted to the ortho).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sklearn.mixture import GaussianMixture

from workbench.texture_seams import rgb_to_lab

from .classifier import CLASSES

GROUND, GRASS = 1, 2
COMPONENTS = 5  # GrabCut's: paving, asphalt and soil; lawns in sun and in shade
MIN_CELLS = 50  # per class, to fit a mixture of COMPONENTS full covariances to
MAX_CELLS = 5000  # per class, drawn at random: 100 a parameter; the fit's time follows it
REG_COVAR = 1.0  # Lab units squared: a colour's spread is never below a unit
OUTLIER_SHARE = 0.05  # of each class's colours drawn from no mixture component
LAB_VOLUME = 100.0 * 256.0 * 256.0  # L 0-100, a and b -128-127
CHUNK_CELLS = 1 << 16  # cells scored at once: a few MB of the mixtures' terms


@dataclass
class FlatColours:
    """The two colour models: ``ground`` and ``grass``, fitted mixtures over Lab."""

    ground: GaussianMixture
    grass: GaussianMixture
    cells: dict

    def record(self) -> dict:
        return {"used": True, "components": COMPONENTS, "training_cells": self.cells}


def fit_flat_colours(rgb: np.ndarray, labels: np.ndarray, seed: int) -> tuple:
    """Gaussian mixtures of the ground and grass training colours.

    Parameters
    ----------
    rgb : (N, 3) uint8
        Colours of the training cells.
    labels : (N,) int
        Their class codes 1-4.
    seed : int
        The draw of at most ``MAX_CELLS`` cells per class and the mixtures'
        initialisation.

    Returns
    -------
    :class:`FlatColours`, or None and why (fewer than ``MIN_CELLS`` of either class),
    and a record for ``fusion.json``.
    """
    models, cells = {}, {}
    rng = np.random.default_rng(seed)
    for code, name in ((GROUND, "ground"), (GRASS, "grass")):
        idx = np.flatnonzero(labels == code)
        cells[name] = len(idx)
        if len(idx) > MAX_CELLS:
            idx = np.sort(rng.choice(idx, MAX_CELLS, replace=False))
        x = rgb_to_lab(rgb[idx]).astype(np.float64)
        if len(x) < MIN_CELLS:
            return None, {"used": False, "reason": f"fewer than {MIN_CELLS} {name} "
                          "cells under the training strokes"}  # fmt: skip
        models[name] = GaussianMixture(
            COMPONENTS, covariance_type="full", reg_covar=REG_COVAR, random_state=seed
        ).fit(x)
    model = FlatColours(models["ground"], models["grass"], cells)
    return model, model.record()


def robust_log_likelihood(mixture: GaussianMixture, lab: np.ndarray) -> np.ndarray:
    """(N,) log density of the colours ``lab`` (N, 3) under ``mixture`` with a share
    ``OUTLIER_SHARE`` of it uniform over the Lab gamut: a colour far from both classes'
    (one no stroke covers) then weighs neither, where the two Gaussian tails alone would
    pick one by how they happen to fall off."""
    return np.logaddexp(
        np.log1p(-OUTLIER_SHARE) + mixture.score_samples(lab),
        np.log(OUTLIER_SHARE / LAB_VOLUME),
    )


def ground_factor(model: FlatColours, ortho: np.ndarray) -> np.ndarray:
    """(H, W) float32 factor on each cell's ground confidence, in (0, 2); grass takes 2
    minus it. 2 / (1 + L_grass / L_ground) of the cell's ortho colour (H, W, 3) uint8."""
    rgb = ortho.reshape(-1, 3)
    out = np.empty(len(rgb), np.float32)
    for i in range(0, len(rgb), CHUNK_CELLS):
        part = rgb_to_lab(rgb[i : i + CHUNK_CELLS]).astype(np.float64)
        diff = robust_log_likelihood(model.grass, part) - robust_log_likelihood(model.ground, part)
        out[i : i + CHUNK_CELLS] = 2.0 / (1.0 + np.exp(np.clip(diff, -50.0, 50.0)))
    return out.reshape(ortho.shape[:2])


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

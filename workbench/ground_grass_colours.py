"""Colour models of ground and grass: Gaussian mixtures in CIE Lab of the ortho's colours
under the training strokes of each class, and each cell's ground factor from them (the
fusion's :mod:`fusion.flat_colours` and the LOD path's labelling weigh ground against
grass by it).

Both classes lie flat on the terrain, so only colour separates them, and a classifier
that reads a patch (the fusion's forest, the LOD path's filter bank) blurs their border.
A cell's own colour under the two mixtures (GrabCut's colour models, Rother et al. 2004)
is a second expert on it (Hinton 2002).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sklearn.mixture import GaussianMixture

from .raster import GRASS, GROUND
from .texture_seams import rgb_to_lab

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
    and a record for the run's JSON (``fusion.json``, ``model.json``).
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

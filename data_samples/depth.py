"""Depth maps as dense matching gives them, not as a perfect renderer does.

From the true z-depth: corners are rounded (smoothing across depth edges), the
background beside occluding edges (on the side the stereo partner, displaced along
the image x axis, cannot see) and textureless shadows become holes, and
Gaussian noise growing with the square of the depth plus gross outliers are added.
"""

from __future__ import annotations

import cv2
import numpy as np


def _blur_valid(depth: np.ndarray, sigma: float) -> np.ndarray:
    valid = np.isfinite(depth).astype(np.float64)
    filled = np.where(valid > 0, depth, 0.0)
    num = cv2.GaussianBlur(filled, (0, 0), sigma)
    den = cv2.GaussianBlur(valid, (0, 0), sigma)
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / den


def depth_edges(depth: np.ndarray, jump: float = 0.5, rel: float = 0.02):
    """Masks of depth discontinuities, each (H, W) bool.

    Returns
    -------
    edge : pixels next to a jump in any direction
    occluded : pixels just right of a nearer surface (their left neighbour is nearer):
        the background a stereo partner displaced along the image x axis cannot see
    """
    d = np.where(np.isfinite(depth), depth, np.inf)
    occluded = np.zeros(d.shape, bool)
    edge = np.zeros(d.shape, bool)
    for axis in (0, 1):
        for shift in (1, -1):
            nb = np.roll(d, shift, axis=axis)
            with np.errstate(invalid="ignore"):
                diff = d - nb
            thr = np.maximum(jump, rel * np.minimum(d, nb))
            big = np.abs(diff) > thr
            big &= np.isfinite(d) | np.isfinite(nb)
            edge |= big
            if axis == 1 and shift == 1:  # nb is the left neighbour
                occluded |= big & (diff > 0)
    return edge, occluded


def degrade_depth(
    depth: np.ndarray,
    gray: np.ndarray,
    lit: np.ndarray,
    rng: np.random.Generator,
    *,
    sigma: float,
    reference_depth: float,
    outliers: float,
    round_edges: bool = True,
) -> np.ndarray:
    """Turn a true z-depth map into a dense-matching-like one.

    Parameters
    ----------
    depth : (H, W) float
        True z-depth, metres; NaN where nothing was hit.
    gray : (H, W) uint8
        The rendered image, for texture-dependent holes.
    lit : (H, W) bool
        Sunlit pixels (False in shadow).
    rng : numpy.random.Generator
    sigma : float
        Noise standard deviation at ``reference_depth``, metres; it grows as depth^2.
    reference_depth : float
        Depth at which the noise is ``sigma`` (the flying height), metres.
    outliers : float
        Fraction of valid pixels replaced by gross errors.
    round_edges : bool
        Smooth across depth edges (False: sharp edges, the holes and noise kept).

    Returns
    -------
    (H, W) float32 depth map, NaN where matching would fail.
    """
    out = depth.astype(np.float64).copy()
    edge, occluded = depth_edges(depth)
    if round_edges:
        band = cv2.dilate(edge.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        out[band] = _blur_valid(depth, 1.5)[band]
    # occlusion holes extend a few pixels to the right of the nearer surface's edge
    holes = cv2.dilate(occluded.astype(np.uint8), np.ones((1, 7), np.uint8), anchor=(0, 0))
    holes = holes.astype(bool)
    g = gray.astype(np.float64)
    local_std = np.sqrt(np.maximum(cv2.blur(g * g, (7, 7)) - cv2.blur(g, (7, 7)) ** 2, 0))
    dark_flat = (~lit) & (local_std < 1.5) & (g < 60)  # only the darkest, flattest shadows
    dark_flat = cv2.morphologyEx(dark_flat.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3)))
    holes |= dark_flat.astype(bool)
    s = sigma * (np.nan_to_num(out, nan=reference_depth) / reference_depth) ** 2
    out = out + rng.normal(0.0, 1.0, out.shape) * s
    valid = np.isfinite(out) & ~holes
    bad = valid & (rng.random(out.shape) < outliers)
    out[bad] *= rng.uniform(0.75, 1.25, int(bad.sum()))
    out[~valid] = np.nan
    return out.astype(np.float32)


def depth_error_stats(
    depth: np.ndarray, true_depth: np.ndarray, *, sigma: float, reference_depth: float
) -> dict:
    """How a depth map departs from the true depth, in units of the noise model.

    Parameters
    ----------
    depth, true_depth : (H, W) float
        Depth map and true z-depth (metres, NaN unknown).
    sigma, reference_depth : float
        The noise model of :func:`degrade_depth`.

    Returns
    -------
    dict
        ``noise_ratio``: robust standard deviation of the normalised residual on smooth
        surfaces (1 when the map follows the model; metres when ``sigma`` is 0);
        ``outlier_fraction``: share of those residuals beyond 8 sigma;
        ``valid_fraction``: share of the truly seen pixels that have a depth.
    """
    seen = np.isfinite(true_depth)
    ok = np.isfinite(depth) & seen
    t = np.nan_to_num(true_depth)
    gy, gx = np.gradient(t)
    # corners are rounded near depth edges on purpose: judge the noise on smooth surfaces
    smooth = ok & (np.hypot(gx, gy) < 0.05 * np.where(seen, t, 1.0))
    # without noise (sigma 0, the floors' samples) the residual is judged in metres
    scale = sigma * (t[smooth] / reference_depth) ** 2 if sigma > 0 else 1.0
    z = (depth[smooth] - t[smooth]) / scale
    mad = np.median(np.abs(z - np.median(z))) if z.size else np.nan
    return {
        "noise_ratio": float(1.4826 * mad),
        "outlier_fraction": float(np.mean(np.abs(z) > 8)) if z.size else float("nan"),
        "valid_fraction": float(ok.sum() / max(seen.sum(), 1)),
    }

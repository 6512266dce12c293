"""Sigma Points covariance descriptors (Kluckner & Bischof 2010, eq. 1).

Per pixel, the mean mu and covariance Sigma of d = 6 cues over an 11 x 11 patch
(CIELab L, a, b; the two first derivatives of L; elevation above ground) become
2d + 1 = 13 points p0 = mu, p_i = mu + alpha (sqrt Sigma)_i, p_{i+d} = mu - alpha
(sqrt Sigma)_i with alpha = sqrt(2d) and the Cholesky factor as square root:
78 attributes. Means and covariances come from box filters over the whole image.
"""

from __future__ import annotations

import cv2
import numpy as np

N_CUES = 6
N_FEATURES = N_CUES * (2 * N_CUES + 1)  # 78
MEAN_ELEVATION = N_CUES - 1  # the attribute of the patch's mean elevation (point p0, last cue)


def feature_cues(rgb: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """The six cues of each pixel.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        Image.
    elevation : (H, W) float
        Height above ground of the surface seen by each pixel, metres (no NaN).

    Returns
    -------
    (H, W, 6) float32: L, a, b (CIELab, L in 0-100), dL/dx, dL/dy, elevation.
    """
    lab = cv2.cvtColor(rgb.astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab)
    L = lab[..., 0]
    dx = cv2.Sobel(L, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    dy = cv2.Sobel(L, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return np.dstack([lab, dx, dy, elevation.astype(np.float32)])


def sigma_points(cues: np.ndarray, patch: int = 11, alpha: float | None = None) -> np.ndarray:
    """Sigma Points descriptor of every pixel.

    Parameters
    ----------
    cues : (H, W, d) float
        Per-pixel cues.
    patch : int
        Side of the square patch, pixels (11 in the paper).
    alpha : float, optional
        Weight of the covariance; sqrt(2 d) by default, as in the paper.

    Returns
    -------
    (H, W, d (2 d + 1)) float32: p0 = mu, then mu + alpha L_i and mu - alpha L_i for
    each column L_i of the Cholesky factor of the patch covariance.
    """
    H, W, d = cues.shape
    alpha = np.sqrt(2 * d) if alpha is None else alpha
    # float64 and centred cues: E[xy] - E[x]E[y] cancels badly otherwise
    offset = cues.reshape(-1, d).astype(np.float64).mean(axis=0)
    c = cues.astype(np.float64) - offset
    box = dict(ddepth=-1, ksize=(patch, patch), normalize=True, borderType=cv2.BORDER_REFLECT)
    mu = [cv2.boxFilter(c[..., i], **box) for i in range(d)]
    cov = {}
    for i in range(d):
        for j in range(i + 1):
            cov[i, j] = cv2.boxFilter(c[..., i] * c[..., j], **box) - mu[i] * mu[j]
    del c  # a view's moments and factors are most of fusion's memory: free them early
    # a small ridge keeps flat patches (zero variance) positive definite
    ridge = 1e-6 * np.maximum(sum(cov[i, i] for i in range(d)) / d, 1e-4)
    chol = cholesky_images(cov, d, ridge)
    del cov, ridge
    out = np.empty((H, W, 2 * d + 1, d), np.float32)
    for k in range(d):
        m = mu[k] + offset[k]
        out[..., 0, k] = m
        for i in range(d):  # point i: mu + alpha * column i of the factor (L[k, i], k >= i)
            step = alpha * chol[k, i] if k >= i else 0.0
            out[..., 1 + i, k] = m + step
            out[..., 1 + d + i, k] = m - step
    return out.reshape(H, W, d * (2 * d + 1))


def cholesky_images(cov: dict, d: int, ridge: np.ndarray) -> dict:
    """Cholesky factors of a covariance per pixel, on images (no (H, W, d, d) arrays).

    Parameters
    ----------
    cov : dict (i, j) -> (H, W) array for j <= i
        Lower triangle of the covariance.
    d : int
    ridge : (H, W) array added to the diagonal.

    Returns
    -------
    dict (i, j) -> (H, W) array, j <= i: the lower-triangular factor L with L L^T = cov.
    Pivots that rounding leaves non-positive are clamped to the ridge rather than failing.
    """
    L = {}
    for j in range(d):
        acc = cov[j, j] + ridge - sum(L[j, k] ** 2 for k in range(j))
        L[j, j] = np.sqrt(np.maximum(acc, ridge))
        inv = 1.0 / L[j, j]
        for i in range(j + 1, d):
            L[i, j] = (cov[i, j] - sum(L[i, k] * L[j, k] for k in range(j))) * inv
    return L

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
CHUNK_PIXELS = 4096  # pixels whose 13 points are written at once: 1.3 MB of float32


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


def sigma_points(
    cues: np.ndarray,
    patch: int = 11,
    alpha: float | None = None,
    pixels: np.ndarray | None = None,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Sigma Points descriptor of every pixel, or of some.

    Parameters
    ----------
    cues : (H, W, d) float
        Per-pixel cues.
    patch : int
        Side of the square patch, pixels (11 in the paper).
    alpha : float, optional
        Weight of the covariance; sqrt(2 d) by default, as in the paper.
    pixels : (N,) int, optional
        Flat indices of the pixels to describe (default all).
    out : (N, F) float32, optional, F >= d (2 d + 1)
        Where to write the descriptors of ``pixels``: its first d (2 d + 1) columns
        (the caller's own columns may follow).

    Returns
    -------
    (H, W, d (2 d + 1)) float32, or ``out`` (or a new (N, d (2 d + 1))) with
    ``pixels``: p0 = mu, then mu + alpha L_i and mu - alpha L_i for each column L_i of
    the Cholesky factor of the patch covariance.
    """
    H, W, d = cues.shape
    n_features = d * (2 * d + 1)
    alpha = np.sqrt(2 * d) if alpha is None else alpha
    # float64 and centred cues: E[xy] - E[x]E[y] cancels badly otherwise; one plane per
    # cue, contiguous, for OpenCV's box filter
    offset = cues.reshape(-1, d).astype(np.float64).mean(axis=0)
    c = np.moveaxis(cues, -1, 0).astype(np.float64) - offset[:, None, None]
    box = dict(ddepth=-1, ksize=(patch, patch), normalize=True, borderType=cv2.BORDER_REFLECT)
    mu = np.stack([cv2.boxFilter(c[i], **box).ravel() for i in range(d)], axis=1)  # (H*W, d)
    moment = {}  # (i, j) -> the patch mean of c_i c_j, j <= i
    for i in range(d):
        for j in range(i + 1):
            moment[i, j] = cv2.boxFilter(c[i] * c[j], **box).ravel()
    del c  # a view's moments and factors are most of fusion's memory: free them early
    n = H * W if pixels is None else len(pixels)
    if out is None:
        out = np.empty((n, n_features), np.float32)
    points = out[:, :n_features].reshape(n, 2 * d + 1, d)
    # the factors and the 13 points of a few thousand pixels at a time: written pixel by
    # pixel, the (N, 13, d) output would be strided writes over the whole image, most
    # of this function's time; a chunk's stays in the cache
    for start in range(0, n, CHUNK_PIXELS):
        s = slice(start, start + CHUNK_PIXELS)
        at = s if pixels is None else pixels[s]
        m = mu[at]
        cov = {(i, j): v[at] - m[:, i] * m[:, j] for (i, j), v in moment.items()}
        # a small ridge keeps flat patches (zero variance) positive definite
        ridge = 1e-6 * np.maximum(sum(cov[i, i] for i in range(d)) / d, 1e-4)
        steps = np.zeros((len(m), d, d))  # [:, i, k]: alpha times the factor's L[k, i]
        for (k, i), factor in cholesky_images(cov, d, ridge).items():
            steps[:, i, k] = alpha * factor
        mean = m + offset
        points[s, 0] = mean
        points[s, 1 : 1 + d] = mean[:, None] + steps
        points[s, 1 + d :] = mean[:, None] - steps
    return out.reshape(H, W, n_features) if pixels is None else out


def cholesky_images(cov: dict, d: int, ridge: np.ndarray) -> dict:
    """Cholesky factors of a covariance per pixel, on images (no (H, W, d, d) arrays).

    Parameters
    ----------
    cov : dict (i, j) -> array for j <= i
        Lower triangle of the covariance, arrays of one shape (an image, or pixels).
    d : int
    ridge : array of that shape, added to the diagonal.

    Returns
    -------
    dict (i, j) -> array of that shape, j <= i: the lower-triangular factor L with L L^T = cov.
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

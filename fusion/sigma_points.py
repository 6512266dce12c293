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
    # float64 and centred cues: E[xy] - E[x]E[y] cancels badly otherwise, and a
    # covariance that comes out slightly indefinite has no Cholesky factor
    offset = cues.reshape(-1, d).astype(np.float64).mean(axis=0)
    c = cues.astype(np.float64) - offset
    box = dict(ddepth=-1, ksize=(patch, patch), normalize=True, borderType=cv2.BORDER_REFLECT)
    mu = np.dstack([cv2.boxFilter(c[..., i], **box) for i in range(d)])
    cov = np.empty((H, W, d, d), np.float64)
    for i in range(d):
        for j in range(i, d):
            e = cv2.boxFilter(c[..., i] * c[..., j], **box) - mu[..., i] * mu[..., j]
            cov[..., i, j] = e
            cov[..., j, i] = e
    # a small ridge keeps flat patches (zero variance) positive definite
    ridge = 1e-6 * np.maximum(np.trace(cov, axis1=-2, axis2=-1) / d, 1e-4)
    idx = np.arange(d)
    cov[..., idx, idx] += ridge[..., None]
    chol = np.linalg.cholesky(cov).astype(np.float32)  # columns are (sqrt Sigma)_i
    mu = (mu + offset).astype(np.float32)  # undo the centring
    out = np.empty((H, W, 2 * d + 1, d), np.float32)
    out[..., 0, :] = mu
    cols = np.swapaxes(chol, -1, -2) * np.float32(alpha)  # row i = alpha * column i
    np.add(mu[..., None, :], cols, out=out[..., 1 : d + 1, :])
    np.subtract(mu[..., None, :], cols, out=out[..., d + 1 :, :])
    return out.reshape(H, W, d * (2 * d + 1))

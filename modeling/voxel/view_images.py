"""The aerial images of a scene as the voxel path samples them: colours for
photo-consistency (HSL hue and saturation as the paper, or CIE Lab; eq. 2-3) and CIE Lab
for seam costs (eq. 5).

Images are read on demand and kept while they fit in a memory budget; the photo-
consistency colours are converted and blurred around the pixels asked for only.
"""

from __future__ import annotations

import cv2
import numpy as np

from workbench.scene import View
from workbench.texture_seams import SceneImages, bilinear, rgb_to_lab


def footprint_sigma(half_width: int) -> float:
    """sigma_c of the Gaussian over a window of half-width ``half_width`` pixels (eq. 2).

    The paper's "known estimate 0.3/(s^2 - 1) + 0.8" is OpenCV's rule for the sigma of a
    kernel of size k = 2s + 1, 0.3((k - 1)/2 - 1) + 0.8, garbled in print: we use the rule.
    """
    return 0.3 * (half_width - 1) + 0.8


def hs_chroma(rgb: np.ndarray) -> np.ndarray:
    """Hue and saturation of HSL as the chroma vector S (cos H, sin H).

    Parameters
    ----------
    rgb : (H, W, 3) uint8

    Returns
    -------
    (H, W, 2) float32 in [-1, 1]. The vector form keeps H and S (and drops lightness,
    as the paper does against changing daylight), makes hue's wrap-around harmless, and
    lets greys, whose hue means nothing, count as the zero vector.
    """
    hls = cv2.cvtColor(rgb.astype(np.float32) / 255.0, cv2.COLOR_RGB2HLS)
    h = np.deg2rad(hls[..., 0])
    s = hls[..., 2]
    return np.stack([s * np.cos(h), s * np.sin(h)], axis=-1).astype(np.float32)


def lab_features(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 CIE Lab scaled by 1/100 (L 0-1), for photo-consistency."""
    return rgb_to_lab(rgb) / 100.0


CONSISTENCY_FEATURES = {"hs": hs_chroma, "lab": lab_features}


class ViewImages(SceneImages):
    """Lazy, cached access to the views' pixels (:class:`~workbench.texture_seams.
    SceneImages`), with the colours the voxel path compares.

    Parameters
    ----------
    views : list of View
    budget_mb : float
        Memory for the images kept.
    features : {"lab", "hs"}
        Colours of the photo-consistency: CIE Lab / 100, or HSL's S (cos H, sin H).
    """

    def __init__(self, views: list[View], budget_mb: float = 1024.0, features: str = "lab"):
        super().__init__(views, budget_mb)
        self._features = CONSISTENCY_FEATURES[features]

    def consistency_samples(self, k: int, uv: np.ndarray, half_width: np.ndarray) -> np.ndarray:
        """Gaussian-weighted colours c_ik of eq. 2 at ``uv`` (N, 2), window half-widths
        (N,) int pixels -> (N, C) float32.

        Only the part of the image around ``uv`` is converted and blurred, with a margin
        of the window and the bilinear neighbour: the values there are those of the
        whole image blurred (at the image's edge the crop's edge is the image's).
        """
        rgb = self.rgb(k)
        h, w = rgb.shape[:2]
        out = None
        for s in np.unique(half_width):
            sel = half_width == s
            at = uv[sel]
            m = int(s) + 2
            x0, y0 = (max(int(np.floor(at[:, i].min())) - m, 0) for i in (0, 1))
            x1 = min(int(np.ceil(at[:, 0].max())) + m + 1, w)
            y1 = min(int(np.ceil(at[:, 1].max())) + m + 1, h)
            img = self._features(rgb[y0:y1, x0:x1])
            if s > 0:
                size = 2 * int(s) + 1
                img = cv2.GaussianBlur(img, (size, size), footprint_sigma(int(s)))
            samples = bilinear(img, at - np.array([x0, y0]))
            if out is None:
                out = np.empty((len(uv), samples.shape[1]), np.float32)
            out[sel] = samples
        return out

    def lab_samples(self, k: int, uv: np.ndarray) -> np.ndarray:
        """CIE Lab colour of view ``k`` at ``uv`` (N, 2), bilinear -> (N, 3) float32."""
        return rgb_to_lab(bilinear(self.rgb(k), uv))

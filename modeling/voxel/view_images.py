"""The aerial images of a scene as the voxel path samples them: colours for
photo-consistency (HSL hue and saturation as the paper, or CIE Lab; eq. 2-3) and CIE Lab
for seam costs (eq. 5).

Images are read once and kept; Gaussian-blurred photo-consistency images are made on
demand, one per (view, window half-width), and kept while they fit in a memory budget.
"""

from __future__ import annotations

from collections import OrderedDict

import cv2
import numpy as np

from workbench.scene import View
from workbench.texture_seams import bilinear, rgb_to_lab


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


class ViewImages:
    """Lazy, cached access to the views' pixels.

    Parameters
    ----------
    views : list of View
    budget_mb : float
        Memory for blurred images; the least recently used go first.
    features : {"lab", "hs"}
        Colours of the photo-consistency: CIE Lab / 100, or HSL's S (cos H, sin H).
    """

    def __init__(self, views: list[View], budget_mb: float = 512.0, features: str = "lab"):
        self.views = views
        self._features = CONSISTENCY_FEATURES[features]
        self._rgb: dict[int, np.ndarray] = {}
        self._blurred: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._budget = budget_mb * 2**20
        self._bytes = 0

    def rgb(self, k: int) -> np.ndarray:
        """(H, W, 3) uint8 image of view ``k``."""
        if k not in self._rgb:
            self._rgb[k] = self.views[k].read_image()
        return self._rgb[k]

    def consistency_image(self, k: int, half_width: int) -> np.ndarray:
        """(H, W, C) photo-consistency colours of view ``k`` averaged over the Gaussian
        window of eq. 2 of half-width ``half_width`` pixels."""
        key = (k, half_width)
        if key in self._blurred:
            self._blurred.move_to_end(key)
            return self._blurred[key]
        img = self._features(self.rgb(k))
        if half_width > 0:
            size = 2 * half_width + 1
            img = cv2.GaussianBlur(img, (size, size), footprint_sigma(half_width))
        self._blurred[key] = img
        self._bytes += img.nbytes
        while self._bytes > self._budget and len(self._blurred) > 1:
            _, old = self._blurred.popitem(last=False)
            self._bytes -= old.nbytes
        return img

    def release_blurred(self) -> None:
        """Drop the blurred images (the proxies need them, the textures do not)."""
        self._blurred.clear()
        self._bytes = 0

    def consistency_samples(self, k: int, uv: np.ndarray, half_width: np.ndarray) -> np.ndarray:
        """Gaussian-weighted colours c_ik of eq. 2 at ``uv`` (N, 2), window half-widths
        (N,) int pixels -> (N, C) float32."""
        out = None
        for s in np.unique(half_width):
            sel = half_width == s
            samples = bilinear(self.consistency_image(k, int(s)), uv[sel])
            if out is None:
                out = np.empty((len(uv), samples.shape[1]), np.float32)
            out[sel] = samples
        return out

    def lab_samples(self, k: int, uv: np.ndarray) -> np.ndarray:
        """CIE Lab colour of view ``k`` at ``uv`` (N, 2), bilinear -> (N, 3) float32."""
        return rgb_to_lab(bilinear(self.rgb(k), uv))

    def rgb_samples(self, k: int, uv: np.ndarray) -> np.ndarray:
        """RGB of view ``k`` at ``uv`` (N, 2), bilinear -> (N, 3) float32 0-255."""
        return bilinear(self.rgb(k), uv)

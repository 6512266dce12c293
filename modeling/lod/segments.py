"""Line segments outlining the roof patches (the LOD paper, section 5.2): from the ortho,
from the height map and from the normal map's directional variation (LSD on each), and
the building's outline (the facades), regularised to the facade directions."""

from __future__ import annotations

import cv2
import numpy as np


def detect_segments(image: np.ndarray) -> np.ndarray:
    """(S, 4) x0, y0, x1, y1 in cells (column, row) of OpenCV's line segment detector
    (LSD, von Gioi et al.) on a float image scaled to 0-255."""
    img = np.nan_to_num(image.astype(np.float64), nan=np.nanmedian(image) if
                        np.isfinite(image).any() else 0.0)  # fmt: skip
    lo, hi = np.percentile(img, [1, 99])
    g = np.clip((img - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    lines = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD).detect(g)[0]
    return np.zeros((0, 4)) if lines is None else lines.reshape(-1, 4).astype(np.float64)


def direction_maps(normal: np.ndarray, theta: float) -> tuple[np.ndarray, np.ndarray]:
    """The two directional normal variation maps: the normal map's dot products with the
    facade directions theta and theta + 90 degrees (ridges stand out in them)."""
    d1 = np.array([np.cos(theta), np.sin(theta)])
    d2 = np.array([-d1[1], d1[0]])
    # the grid's rows run south: a normal's y is minus the row direction
    return (normal[0] * d1[0] + normal[1] * d1[1], normal[0] * d2[0] + normal[1] * d2[1])


def outline_segments(mask: np.ndarray, epsilon: float = 1.0) -> np.ndarray:
    """(S, 4) the building's outline as segments in cells: its contours simplified by
    ``epsilon`` cells (the facade segments of a 2.5D grid)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_CCOMP,
                                   cv2.CHAIN_APPROX_NONE)  # fmt: skip
    out = []
    for c in contours:
        p = cv2.approxPolyDP(c, epsilon, True).reshape(-1, 2).astype(np.float64)
        if len(p) >= 2:
            out.append(np.column_stack([p, np.roll(p, -1, axis=0)]))
    return np.concatenate(out) if out else np.zeros((0, 4))


def regularise_segments(
    seg: np.ndarray, theta: float, angle_deg: float, collinear: float, min_length: float
) -> tuple[np.ndarray, np.ndarray]:
    """The two steps of the regularisation (the paper after Zhu et al.): segments within
    ``angle_deg`` of a facade direction are turned onto it about their middle, then those
    of one direction whose lines lie within ``collinear`` of each other are merged into one
    (offset weighted by length, extent their union); others shorter than ``min_length``
    are dropped.

    Parameters
    ----------
    seg : (S, 4) x0, y0, x1, y1 in cells, image axes (rows down)
    theta : facade direction, radians, world axes (y north)

    Returns
    -------
    segments : (S', 4)
    regular : (S',) bool, turned onto a facade direction
    """
    if not len(seg):
        return seg, np.zeros(0, bool)
    p, q = seg[:, :2], seg[:, 2:]
    d = q - p
    length = np.hypot(d[:, 0], d[:, 1])
    ang = np.mod(np.arctan2(-d[:, 1], d[:, 0]), np.pi)  # world angle of each segment
    out, regular = [], []
    for axis in (theta, theta + np.pi / 2):
        a = np.mod(axis, np.pi)
        off = np.minimum(np.mod(ang - a, np.pi), np.pi - np.mod(ang - a, np.pi))
        sel = off < np.radians(angle_deg)
        if not sel.any():
            continue
        u = np.array([np.cos(a), -np.sin(a)])  # the direction in image axes
        v = np.array([-u[1], u[0]])
        mid = (p[sel] + q[sel]) / 2
        offset, half = mid @ v, length[sel] / 2
        centre = mid @ u
        order = np.argsort(offset)
        groups, cur = [], [order[0]]
        for i in order[1:]:
            if offset[i] - offset[cur[-1]] <= collinear:
                cur.append(i)
            else:
                groups.append(cur)
                cur = [i]
        groups.append(cur)
        for g in groups:
            w = half[g] * 2
            o = float(np.sum(offset[g] * w) / w.sum())
            lo, hi = float((centre[g] - half[g]).min()), float((centre[g] + half[g]).max())
            a0, a1 = lo * u + o * v, hi * u + o * v
            out.append([*a0, *a1])
            regular.append(True)
        length[sel] = 0  # taken
    rest = length >= min_length
    out += seg[rest].tolist()
    regular += [False] * int(rest.sum())
    return np.asarray(out, np.float64).reshape(-1, 4), np.asarray(regular, bool)

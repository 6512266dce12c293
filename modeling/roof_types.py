"""A roof type label from a building's roof planes."""

from __future__ import annotations

import numpy as np

ROOF_TYPES = ("flat", "shed", "gable", "hipped", "pyramid", "mansard", "multi-level", "complex")


def roof_type(
    planes: np.ndarray,
    areas: np.ndarray,
    heights: np.ndarray,
    outline_z: np.ndarray,
    flat_deg: float = 5.0,
) -> str:
    """Name the roof of a building from its planes.

    Parameters
    ----------
    planes : (P, 4)
        Roof planes (unit normal up, offset).
    areas : (P,)
        Roof area of each plane, square metres.
    heights : (P,)
        Mean roof height of each plane, metres.
    outline_z : (K,)
        Roof heights at the vertices of the building outline, metres: constant along a
        hipped roof's eaves, rising to the ridge at a gable's ends.
    flat_deg : float
        Slopes below this count as flat.

    Returns
    -------
    One of ROOF_TYPES. Planes under 8 % of the roof area are ignored (dormers, noise).
    """
    keep = areas >= 0.08 * areas.sum()
    planes, heights = planes[keep], heights[keep]
    slope = np.degrees(np.arccos(np.clip(planes[:, 2], -1, 1)))
    sloped = slope >= flat_deg
    if not sloped.any():
        levels = np.unique(np.round(heights / 1.0))
        return "flat" if len(levels) == 1 else "multi-level"
    azimuth = np.degrees(np.arctan2(planes[sloped, 0], planes[sloped, 1])) % 360
    sectors = np.unique(np.round(azimuth / 90.0).astype(int) % 4)
    pitches = slope[sloped]
    rise = float(heights.max() - outline_z.min())
    level_eaves = np.ptp(outline_z) < 0.3 * max(rise, 1e-6)
    if not level_eaves:  # gable ends or a shed's high side
        return "shed" if len(sectors) == 1 else "gable"
    if len(sectors) == 4 or (~sloped).any():
        if pitches.max() - pitches.min() > 15 or ((~sloped).any() and sloped.sum() >= 4):
            return "mansard"
        return "pyramid" if sloped.sum() == 4 and _apex(planes[sloped]) else "hipped"
    return "complex"


def _apex(planes: np.ndarray) -> bool:
    """Four planes that meet near one point (a pyramid) rather than along a ridge."""
    A, b = planes[:, :3], -planes[:, 3]
    p, *_ = np.linalg.lstsq(A, b, rcond=None)
    return bool(np.max(np.abs(A @ p - b)) < 0.3)

"""A roof type label from a building's roof planes."""

from __future__ import annotations

import numpy as np

ROOF_TYPES = (
    "flat", "shed", "gable", "hipped", "pyramid", "mansard", "multi-level", "complex",
    "dissymmetric", "platform",  # the variational paper's roofs (the parametric path)
)  # fmt: skip


# a mansard's lower faces are steeper than this
STEEP_DEG = 55.0


def roof_type(
    planes: np.ndarray,
    areas: np.ndarray,
    heights: np.ndarray,
    outline_z: np.ndarray,
    ridge_z: float | None = None,
    centre: tuple[float, float, float] | None = None,
    flat_deg: float = 5.0,
    steep_deg: float = STEEP_DEG,
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
        Roof heights at the vertices of the building outline, metres: level along a
        hipped roof's eaves, rising to the ridge at a gable's ends.
    ridge_z : float, optional
        Highest point of the roof, metres (default: the highest plane's mean height).
    centre : (x, y, size), optional
        The footprint's centroid and the square root of its area, metres. Four hips meet
        in one point on an L-shaped hipped roof too, but a pyramid's apex lies over its
        centre (within 15 % of its size).
    flat_deg : float
        Slopes below this count as flat.
    steep_deg : float
        Slopes above this are a mansard's lower faces when a flatter roof lies above them.

    Returns
    -------
    One of ROOF_TYPES. Planes under 8 % of the roof area are ignored (dormers, noise).
    The eaves are level when the outline's high vertices (its 90th percentile) stay in
    the lower half of the rise from the outline's median height to the ridge: a gable's
    ends reach the ridge, while a hipped roof's outline only wanders by the little its
    edges lie off the walls (a 40-degree roof drops 0.4 m over half a metre).
    """
    keep = areas >= 0.08 * areas.sum()
    planes, heights, areas = planes[keep], heights[keep], areas[keep]
    slope = np.degrees(np.arccos(np.clip(planes[:, 2], -1, 1)))
    sloped = slope >= flat_deg
    if not sloped.any():
        levels = np.unique(np.round(heights / 1.0))
        return "flat" if len(levels) == 1 else "multi-level"
    steep = slope >= steep_deg
    if steep.any() and (~steep).any() and heights[~steep].mean() > heights[steep].mean():
        return "mansard"  # steep lower faces under a flatter top
    # the sides the planes face, in quarters turned from the largest one's: in the
    # world's quarters a roof turned by 45 degrees straddled them (a hipped roof's four
    # faces fell in two quarters, "complex")
    azimuth = np.degrees(np.arctan2(planes[sloped, 0], planes[sloped, 1]))
    turned = (azimuth - azimuth[np.argmax(areas[sloped])]) % 360
    sectors = np.unique(np.round(turned / 90.0).astype(int) % 4)
    ridge = max(float(heights.max()), -np.inf if ridge_z is None else float(ridge_z))
    eave = float(np.median(outline_z))
    level_eaves = np.quantile(outline_z, 0.9) - eave < 0.5 * max(ridge - eave, 1e-6)
    if not level_eaves:  # gable ends or a shed's high side
        return "shed" if len(sectors) == 1 else "gable"
    if len(sectors) >= 3:
        pyramid = sloped.sum() == 4 and _apex(planes[sloped], centre)
        return "pyramid" if pyramid else "hipped"
    return "complex"


def _apex(planes: np.ndarray, centre: tuple[float, float, float] | None) -> bool:
    """Four planes that meet near one point (a pyramid) rather than along a ridge, over
    the footprint's centre when it is given."""
    A, b = planes[:, :3], -planes[:, 3]
    p, *_ = np.linalg.lstsq(A, b, rcond=None)
    if np.max(np.abs(A @ p - b)) >= 0.3:
        return False
    return centre is None or bool(np.hypot(p[0] - centre[0], p[1] - centre[1]) < 0.15 * centre[2])

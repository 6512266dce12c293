"""Buildings from the refined classes: connected building super-pixels, split where they
only touch weakly (a morphological opening, as in the LOD paper, section 4.2)."""

from __future__ import annotations

import numpy as np

from modeling.shared.opened_parts import opened_parts


def split_buildings(
    building: np.ndarray, labels: np.ndarray, gsd: float, opening_m: float, min_area_m2: float
) -> np.ndarray:
    """Assign building super-pixels to buildings.

    The building cells are opened with a disc of radius ``opening_m``, which cuts thin
    bridges between neighbouring buildings; each connected part of the opened mask of at
    least ``min_area_m2`` is a building, and each building super-pixel joins the part that
    covers most of its cells (super-pixels the opening removes entirely are dropped).

    Parameters
    ----------
    building : (N,) bool
        Super-pixels labelled building.
    labels : (H, W) int
        Super-pixels 0..N-1.
    gsd : float
        Cell size, metres.

    Returns
    -------
    (N,) int64 building id of every super-pixel, 1..B, 0 for none.
    """
    n = len(building)
    parts, big = opened_parts(building[labels], gsd, opening_m, min_area_m2, connectivity=8)
    on = building[labels] & (parts > 0) & big[parts]
    # the part covering most cells of each super-pixel
    pairs = np.stack([labels[on], parts[on]], axis=1)
    if not len(pairs):
        return np.zeros(n, np.int64)
    uniq, counts = np.unique(pairs, axis=0, return_counts=True)
    order = np.lexsort((-counts, uniq[:, 0]))
    uniq = uniq[order]
    first = np.r_[True, uniq[1:, 0] != uniq[:-1, 0]]
    owner = np.zeros(n, np.int64)
    owner[uniq[first, 0]] = uniq[first, 1]
    # renumber the parts that kept super-pixels 1..B
    kept, owner_ids = np.unique(owner, return_inverse=True)
    return owner_ids.astype(np.int64) if kept[0] == 0 else owner_ids.astype(np.int64) + 1

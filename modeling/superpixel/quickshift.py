"""Quickshift super-pixels on the fused ortho (the super-pixel paper, section 4.1), with the
DSM's height as a fourth channel so that they do not straddle a wall, or on the relief of
the DSM where the ortho cannot tell roof faces apart (LiDAR)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.color import rgb2lab
from skimage.measure import label
from skimage.segmentation import quickshift

from workbench.parallel import ordered_map

RELIEF_LAB = 100.0  # Lab units per unit of a normal's horizontal component


def quickshift_superpixels(
    image: np.ndarray,
    sigma: float = 2.0,
    tau: float = 8.0,
    ratio: float = 1.0,
    tile: int = 512,
    seed: int = 0,
    workers: int = 1,
    height: np.ndarray | None = None,
    height_weight: float = 0.0,
) -> np.ndarray:
    """Quickshift (scikit-image) in CIELab plus pixel position, tile by tile, with
    ``height_weight`` times ``height`` as a fourth channel when given; or, for a float
    ``image`` (e.g. :func:`relief_image`), in its channels as they are.

    Large rasters are cut into tiles of ``tile`` pixels, each segmented with a margin of
    3 tau pixels so that its super-pixels see their whole neighbourhood; the tile keeps the
    labels of its own pixels. Time and memory grow linearly with the area; a super-pixel
    crossing a tile border is cut there.

    Parameters
    ----------
    image : (H, W, 3) uint8 RGB, or (H, W, C) float features
    sigma : float
        Width of the Parzen kernel, pixels (Quickshift's kernel_size).
    tau : float
        Largest distance to a parent in the Quickshift tree (max_dist).
    ratio : float
        Weight of colour against position, in [0, 1].
    tile : int
        Tile size, pixels.
    seed : int
        Seed of Quickshift's tie-breaking noise (the same for every tile).
    workers : int
        Tiles segmented at once, in threads (scikit-image's Quickshift releases the GIL);
        the labels do not depend on it.
    height : (H, W) float, optional
        Heights beside an RGB ``image`` (the DSM), metres; NaN where unknown.
    height_weight : float
        Lab units per metre of ``height`` (:func:`colour_height_image`); 0 segments the
        colour alone, as the paper does.

    Returns
    -------
    (H, W) int64 labels 0..N-1, each super-pixel connected.
    """
    H, W = image.shape[:2]
    lab = image.dtype == np.uint8
    margin = int(np.ceil(3 * tau))
    with_height = lab and height is not None and height_weight > 0
    tiles = [
        (r0, c0, min(H, r0 + tile), min(W, c0 + tile))
        for r0 in range(0, H, tile)
        for c0 in range(0, W, tile)
    ]

    def segment(bounds):
        r0, c0, r1, c1 = bounds
        R0, C0 = max(0, r0 - margin), max(0, c0 - margin)
        R1, C1 = min(H, r1 + margin), min(W, c1 + margin)
        window = image[R0:R1, C0:C1]
        if with_height:
            window = colour_height_image(window, height[R0:R1, C0:C1], height_weight)
        seg = quickshift(
            window,
            ratio=ratio,
            kernel_size=sigma,
            max_dist=tau,
            convert2lab=lab and not with_height,
            rng=seed,
        )
        _, local = np.unique(seg[r0 - R0 : r1 - R0, c0 - C0 : c1 - C0], return_inverse=True)
        return local.reshape(r1 - r0, c1 - c0)

    out = np.empty((H, W), np.int64)
    next_label = 0
    # every tile in flight: the tiles differ in size (the last row and column are cut),
    # and their labels together are no larger than ``out``
    labelled = ordered_map(segment, tiles, workers, in_flight=len(tiles))
    for (r0, c0, r1, c1), local in zip(tiles, labelled, strict=True):
        out[r0:r1, c0:c1] = local + next_label
        next_label += int(local.max()) + 1
    return split_disconnected(out)


def colour_height_image(rgb: np.ndarray, height: np.ndarray, weight: float) -> np.ndarray:
    """(H, W, 4) float: CIELab of ``rgb`` and ``weight`` times ``height``.

    Colour alone lets a super-pixel run from a roof's edge onto the paving below where
    the two look alike (shadow, grey on grey), and the class CRF can then only give the
    whole of it one label. With the height beside the colour a wall's step is far apart
    in Quickshift's space: at 10 Lab units per metre a 0.8 m step is already beyond its
    tau of 8, while a 45-degree roof changes by 2.5 units from one 0.25 m cell to the next.
    Unknown heights (the cells beside walls no view saw) take the nearest known one, so
    that they join the side they are closest to.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    height : (H, W) float
        Metres, NaN unknown.
    weight : float
        Lab units per metre.
    """
    seen = np.isfinite(height)
    if not seen.any():
        filled = np.zeros(height.shape)
    elif seen.all():
        filled = height
    else:
        nearest = ndimage.distance_transform_edt(~seen, return_distances=False, return_indices=True)
        filled = height[tuple(nearest)]
    return np.concatenate([rgb2lab(rgb), weight * filled[..., None]], axis=-1)


def relief_image(dsm: np.ndarray, gsd: float, weight: float = RELIEF_LAB) -> np.ndarray:
    """(H, W, 2) float: the east and north components of the DSM's unit surface normal,
    times ``weight`` (0 where the DSM is unknown).

    A LiDAR ortho (one grey level or intensity per cell) does not tell the two sides of
    a ridge apart the way shading does in aerial photographs, and its noise cuts roofs
    into single cells; the normals do. With the default weight, the faces of a 40-degree
    gable are 128 apart, as far as black from white in CIELab.

    Parameters
    ----------
    dsm : (H, W) float
        Heights, metres (NaN unknown).
    gsd : float
        Cell size, metres.
    """
    seen = np.isfinite(dsm)
    z = np.where(seen, dsm, np.nanmedian(dsm) if seen.any() else 0.0)
    dz_drow, dz_dx = np.gradient(z, gsd)  # rows run south: dz/dy = -dz/drow
    norm = np.sqrt(1.0 + dz_dx**2 + dz_drow**2)
    out = np.stack([-dz_dx / norm, dz_drow / norm], axis=-1) * weight
    out[~seen] = 0.0
    return out


def split_disconnected(labels: np.ndarray) -> np.ndarray:
    """Relabel so that every label is one 4-connected region, labels 0..N-1: the regions
    ordered by their label, then by their first cell in raster order."""
    if not labels.size:
        return np.zeros(labels.shape, np.int64)
    # scikit-image numbers the regions of equal value by their first cell in raster order
    region = label(labels, background=-1, connectivity=1).ravel() - 1
    n = int(region.max()) + 1
    label_of = np.empty(n, np.int64)
    label_of[region] = labels.ravel()
    rank = np.empty(n, np.int64)
    rank[np.argsort(label_of, kind="stable")] = np.arange(n)
    return rank[region].reshape(labels.shape)

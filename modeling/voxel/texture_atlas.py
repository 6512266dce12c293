"""One texture atlas per building: the charts' texel grids packed into one image, and
the texture coordinates of the mesh's triangle corners."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .surface_graph import Chart, SurfaceGraph

_PAD = 1  # texels around each chart, copied from its border against bilinear bleeding
_GREY = (128, 128, 128)


def chart_images(graph: SurfaceGraph, colours: np.ndarray) -> list[np.ndarray]:
    """The texel image of every chart.

    Parameters
    ----------
    graph : SurfaceGraph
    colours : (V, 3) uint8
        Colour of every graph vertex (texel).

    Returns
    -------
    list of (rows + 2 pad, cols + 2 pad, 3) uint8; texels outside the chart's faces
    (and unseen ones, given grey by the caller) take the nearest texel's colour.
    """
    out = []
    for i, chart in enumerate(graph.charts):
        if not chart.visible:  # a floor: one grey texel (and its pad)
            out.append(np.full((1 + 2 * _PAD, 1 + 2 * _PAD, 3), _GREY, np.uint8))
            continue
        rows, cols = chart.shape
        img = np.zeros((rows + 2 * _PAD, cols + 2 * _PAD, 3), np.uint8)
        valid = np.zeros(img.shape[:2], bool)
        sel = graph.chart == i
        img[graph.row[sel] + _PAD, graph.col[sel] + _PAD] = colours[sel]
        valid[graph.row[sel] + _PAD, graph.col[sel] + _PAD] = True
        if not valid.any():
            img[:] = _GREY
        else:
            idx = ndimage.distance_transform_edt(
                ~valid, return_distances=False, return_indices=True
            )
            img = img[idx[0], idx[1]]
        out.append(img)
    return out


def pack_charts(shapes: list[tuple[int, int]]) -> tuple[np.ndarray, tuple[int, int]]:
    """Shelf packing: charts sorted by height fill rows of a near-square atlas.

    Parameters
    ----------
    shapes : list of (rows, cols)

    Returns
    -------
    offsets : (C, 2) int
        Top-left (row, col) of each chart in the atlas.
    size : (rows, cols) of the atlas.
    """
    shapes_a = np.asarray(shapes, np.int64).reshape(-1, 2)
    if not len(shapes_a):
        return np.zeros((0, 2), np.int64), (1, 1)
    width = int(
        max(shapes_a[:, 1].max(), np.ceil(np.sqrt((shapes_a[:, 0] * shapes_a[:, 1]).sum()) * 1.15))
    )
    offsets = np.zeros_like(shapes_a)
    x = y = shelf = 0
    for i in np.argsort(-shapes_a[:, 0], kind="stable"):
        h, w = shapes_a[i]
        if x + w > width:
            x, y, shelf = 0, y + shelf, 0
        offsets[i] = (y, x)
        x += w
        shelf = max(shelf, h)
    return offsets, (int(y + shelf), width)


def atlas(
    graph: SurfaceGraph, colours: np.ndarray, vertices: np.ndarray, triangles: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The atlas image and the texture coordinates of every triangle corner.

    Returns
    -------
    image : (H, W, 3) uint8
    uvs : (T, 3, 2) float
        OBJ texture coordinates (u right, v up, 0-1) of each triangle's corners.
    """
    images = chart_images(graph, colours)
    offsets, (h, w) = pack_charts([img.shape[:2] for img in images])
    image = np.zeros((h, w, 3), np.uint8)
    uvs = np.zeros((len(triangles), 3, 2))
    for chart, img, (r0, c0) in zip(graph.charts, images, offsets, strict=True):
        image[r0 : r0 + img.shape[0], c0 : c0 + img.shape[1]] = img
        if not chart.visible:
            uvs[chart.triangles] = ((c0 + _PAD + 0.5) / w, 1.0 - (r0 + _PAD + 0.5) / h)
            continue
        uvs[chart.triangles] = _corner_uvs(
            chart, vertices[triangles[chart.triangles]], graph.texel_m, r0, c0, (h, w)
        )
    return image, uvs


def _corner_uvs(
    chart: Chart, corners: np.ndarray, texel_m: float, r0: int, c0: int, size
) -> np.ndarray:
    q = corners - chart.origin
    x = q @ chart.u / texel_m + c0 + _PAD
    y = q @ chart.v / texel_m + r0 + _PAD
    h, w = size
    return np.stack([x / w, 1.0 - y / h], axis=-1)

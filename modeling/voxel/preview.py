"""The voxel path's preview: what photo-consistency and the graph cuts did."""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np

from workbench.meshes import concatenate_meshes
from workbench.pictures import colorize_height, contact_sheet
from workbench.raycast import cast, raycasting_scene
from workbench.render import triangle_batches, viewpoints

from .building import Proxy, Texture


def voxel_preview(p: Proxy | None, t: Texture | None, buildings: list, ground) -> np.ndarray:
    """(h, w, 3) uint8 contact sheet: the variance of ``p`` (the largest proxy), heights
    before and after clustering, its roof views before and after the graph cuts (its
    texture ``t``), the textured buildings and the ground texture (``ground``, a
    :class:`~.path.TexturedGround` or None)."""
    if p is None:
        return np.full((64, 64, 3), 255, np.uint8)
    vertical, horiz = p.variance
    var = vertical.T[::-1]  # up is up
    var_img = colorize_height(np.log10(np.where(np.isfinite(var), var, np.nan) + 1e-6))
    horiz_img = colorize_height(np.log10(horiz.T[::-1] + 1e-6))
    tops = p.roof.column_tops(p.frame.r, p.frame.x0, p.frame.y0)
    top = float(np.nanmax(p.min_height)) if np.isfinite(p.min_height).any() else 1.0
    before = _height_image(p.min_height, top)
    after = _height_image(np.where(np.isfinite(tops), tops, np.nan), top)
    row1 = [
        (_upscale(var_img), f"building {p.id}: variance, vertical slice"),
        (_upscale(horiz_img), "variance at the roof"),
        (_upscale(before), "most consistent heights"),
        (_upscale(after), "roof planes" if p.roof.pitched else "after clustering"),
    ]
    top_before = _top_labels(p, t, t.initial)
    top_after = _top_labels(p, t, t.stitched.labels)
    render = render_textured(buildings, ground.surfaces() if ground is not None else [])
    row2 = [
        (top_before, "roof views: best per texel"),
        (top_after, "after graph cuts"),
        (render, "textured proxies"),
    ]
    if ground is not None:
        row2.append((ground.image, "ground texture"))
    return contact_sheet([row1, row2])


def _upscale(img: np.ndarray, size: int = 240) -> np.ndarray:
    h, w = img.shape[:2]
    f = max(1, size // max(h, w))
    return cv2.resize(img, (w * f, h * f), interpolation=cv2.INTER_NEAREST)


def _height_image(z: np.ndarray, top: float) -> np.ndarray:
    """A column height map (nx, ny) in turbo colours from 0 to ``top`` metres, north up."""
    g = np.clip(np.nan_to_num(z.T[::-1], nan=0.0) / max(top, 1e-6) * 255, 0, 255)
    rgb = cv2.cvtColor(cv2.applyColorMap(g.astype(np.uint8), cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    rgb[~np.isfinite(z.T[::-1])] = 0
    return rgb


def _top_labels(proxy: Proxy, tex: Texture, labels: np.ndarray) -> np.ndarray:
    """Roof texels coloured by view, top-down in the building's own frame."""
    g = tex.graph
    roof = (g.normals[:, 2] > 0.5) & (labels >= 0)  # pitched roofs too: walls are below 0.5
    palette = np.random.default_rng(0).integers(40, 255, (int(labels.max()) + 2, 3))
    if not roof.any():
        return np.full((64, 64, 3), 255, np.uint8)
    local = proxy.frame.to_local_xy(g.positions[roof, :2])
    ij = np.round((local - local.min(axis=0)) / g.texel_m).astype(int)  # texel centres
    img = np.full((ij[:, 1].max() + 1, ij[:, 0].max() + 1, 3), 255, np.uint8)
    img[ij[:, 1].max() - ij[:, 1], ij[:, 0]] = palette[labels[roof]].astype(np.uint8)
    return _upscale(img, 240)


RENDER_IMAGE_BYTES = 64 * 2**20  # atlases held at once when drawing the textured buildings


def render_textured(buildings: Iterable, ground: Iterable = (), width: int = 640) -> np.ndarray:
    """Ray-cast picture of the textured buildings (and the ground's textured pieces) from
    the south-west: each pixel's nearest hit is looked up in its mesh's atlas through the
    interpolated UVs. ``buildings`` and ``ground`` are iterated twice (their extent, then
    their meshes a batch of at most ``RENDER_BATCH`` triangles and ``RENDER_IMAGE_BYTES``
    of atlases at a time: a city's atlases are not all held)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for b in buildings:
        lo = np.minimum(lo, b.mesh.vertices.min(axis=0))
        hi = np.maximum(hi, b.mesh.vertices.max(axis=0))
    z = [lo[2], hi[2]]
    for s in ground:
        z = [min(z[0], s.vertices[:, 2].min()), max(z[1], s.vertices[:, 2].max())]
    cam = viewpoints((lo[0], lo[1], hi[0], hi[1]), (float(z[0]), float(z[1])), width,
                     width * 3 // 4)["south-west"]  # fmt: skip
    origin, dirs = cam.pixel_grid_rays()
    img = np.full((cam.height * cam.width, 3), 255, np.uint8)
    nearest = np.full(len(dirs), np.inf)

    def parts():
        for b in buildings:
            m = b.mesh
            yield m.vertices, m.triangles, m.texture.uvs, m.texture.image
        for s in ground:
            yield s.vertices, s.triangles, s.texture.uvs, s.texture.image

    # a city's atlases: some 0.3 MB a building, in the batch together
    for batch in triangle_batches(parts(), image_bytes=RENDER_IMAGE_BYTES):
        V, T, owner = concatenate_meshes([(v, t) for v, t, _, _ in batch])
        uvs = np.concatenate([u for _, _, u, _ in batch])
        hits = cast(raycasting_scene(V, T), origin, dirs)
        closer = (hits.tri >= 0) & (hits.t < nearest)
        nearest[closer] = hits.t[closer]
        for i, (_, _, _, atlas_img) in enumerate(batch):
            sel = np.flatnonzero(closer & (owner[np.maximum(hits.tri, 0)] == i + 1))
            if not len(sel):
                continue
            corners = uvs[hits.tri[sel]]
            b = hits.bary[sel]
            uv = (
                (1 - b[:, :1] - b[:, 1:]) * corners[:, 0]
                + b[:, :1] * corners[:, 1]
                + b[:, 1:] * corners[:, 2]
            )
            h, w = atlas_img.shape[:2]
            c = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
            r = np.clip(((1 - uv[:, 1]) * h).astype(int), 0, h - 1)
            img[sel] = atlas_img[r, c]
    return img.reshape(cam.height, cam.width, 3)

"""Lifting a view's depth map into observations of ortho cells, with visibility.

Each pixel with a depth, less the isolated gross errors of matching
(:func:`depth_outliers`), becomes a world point (camera ray scaled by the z-depth) and
lands in one cell of the ortho grid. Within one view, a cell keeps only the points
of the surface nearest to the camera: points more than a tolerance behind the
nearest point of the same cell (:func:`visibility_groups`) belong to a hidden surface
(seen through a mis-registered edge, or a facade below a roof edge) and are dropped.
Only points of non-steep surfaces set that nearest depth: a facade rising from a cell
is nearer to an oblique camera than the ground in front of it, yet hides none of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.camera import Camera
from workbench.raster import Grid, shifted


@dataclass
class ViewObservations:
    """The observations of one view.

    Attributes
    ----------
    pixels : (N,) int64
        Flat pixel index (row * width + col) of each observation in the view.
    cells : (N,) int64
        Flat cell index (row * grid.width + col) in the ortho grid.
    xyz : (N, 3) float64
        World point, metres.
    depth : (N,) float32
        z-depth, metres.
    visible : (N,) bool
        Kept by the per-cell visibility test.
    normal_z : (N,) float32
        z of the surface normal estimated from the depth map, the normal turned toward
        the camera (1 level and facing up, 0 vertical, negative facing down).
    near_jump : (N,) bool
        Within a few pixels of a depth discontinuity (:func:`depth_jumps`), and not on
        its nearer surface (:func:`near_side`), or behind an occlusion
        (:func:`behind_occlusions`).
    height_weight : (N,) float32
        Weight of the point's height in its cell's median (:func:`height_weights`).
    """

    pixels: np.ndarray
    cells: np.ndarray
    xyz: np.ndarray
    depth: np.ndarray
    visible: np.ndarray
    normal_z: np.ndarray

    near_jump: np.ndarray
    height_weight: np.ndarray

    @property
    def top_surface(self) -> np.ndarray:
        """(N,) bool: visible, away from depth jumps, on a surface facing up (not a
        facade, not the underside of a crown seen by an oblique view)."""
        return self.visible & ~self.near_jump & (self.normal_z > STEEP_NORMAL_Z)


STEEP_NORMAL_Z = 0.26  # cos(75 deg): facades and undersides out, 70 deg mansard slopes in


def normal_z_image(
    camera: Camera,
    depth: np.ndarray,
    *,
    step: int = 3,
    sigma: float = 1.5,
    rays: np.ndarray | None = None,
):
    """(H, W) z of surface normals from a depth map, NaN where unknown.

    The depth is smoothed first (dense-matching noise is as large as a pixel's
    footprint) and differentiated over ``2 step`` pixels on one side of each pixel, the
    straighter (:func:`_one_sided_difference`); a lone unknown pixel takes the
    smoothed depth of its neighbours, so that the normals around it stay known. Each
    normal is turned toward the camera, so a surface the view sees from below has a
    negative z. ``rays``: as for :func:`lift_depth`.
    """
    import cv2

    H, W = depth.shape
    valid = np.isfinite(depth).astype(np.float32)
    d = np.nan_to_num(depth).astype(np.float32)
    num = cv2.GaussianBlur(d, (0, 0), sigma)
    den = cv2.GaussianBlur(valid, (0, 0), sigma)
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = np.where(den > 0.05, num / den, np.nan)
    if rays is None:
        _, rays = camera.pixel_grid_rays()
    # points relative to the camera centre, in float32: half the memory traffic, and
    # millimetres over the few hundred metres of an aerial view; one image per axis
    # (NumPy's loops run along rows, not along (x, y, z) triples)
    P = np.stack([rays[:, k].reshape(H, W).astype(np.float32) * smooth for k in range(3)])
    s = step
    Pp = np.pad(P, ((0, 0), (2 * s, 2 * s), (2 * s, 2 * s)), constant_values=np.nan)
    dx = _one_sided_difference(Pp, s, axis=2)
    dy = _one_sided_difference(Pp, s, axis=1)
    nx = dx[1] * dy[2] - dx[2] * dy[1]
    ny = dx[2] * dy[0] - dx[0] * dy[2]
    n_z = dx[0] * dy[1] - dx[1] * dy[0]
    toward = -np.sign(nx * P[0] + ny * P[1] + n_z * P[2])  # camera at P = 0
    with np.errstate(invalid="ignore", divide="ignore"):
        nz = (toward * n_z / np.sqrt(nx * nx + ny * ny + n_z * n_z)).astype(np.float32)
    nz[:, :s], nz[:, -s:], nz[:s], nz[-s:] = np.nan, np.nan, np.nan, np.nan
    return nz


def _one_sided_difference(Pp: np.ndarray, s: int, axis: int) -> np.ndarray:
    """(3, H, W) the difference of the points over ``2 s`` pixels along ``axis`` (1 rows,
    2 columns), taken on the side whose points lie straighter (the smaller second
    difference over ``s``), NaN where neither side is known. ``Pp``: (3, H + 4 s,
    W + 4 s) the points padded with ``2 s`` NaN on every side.

    A central difference across a convex crease (a roof's edge over its wall) mixes the
    two faces' slopes, and the wall's top pixels, seen by an oblique view, pass for a top
    surface. On the side away from the crease the difference is the pixel's own face's:
    dev fusions of seeds 0-2, DSM RMSE off the height jumps 0.344, 0.395, 0.407 ->
    0.337, 0.371, 0.404 m; dev seeds 6, 7, 10 0.507, 0.672, 0.506 -> 0.453, 0.643,
    0.470 m."""
    m = 2 * s
    H, W = Pp.shape[1] - 2 * m, Pp.shape[2] - 2 * m

    def at(offset: int) -> np.ndarray:  # a view of the points ``offset`` pixels along
        if axis == 1:
            return Pp[:, m + offset : m + offset + H, m : m + W]
        return Pp[:, m : m + H, m + offset : m + offset + W]

    P = at(0)
    ahead, behind = at(m) - P, P - at(-m)
    with np.errstate(invalid="ignore"):
        # second differences over s on each side, squared lengths
        bend_ahead = ((ahead + 2 * (P - at(s))) ** 2).sum(axis=0)
        bend_behind = ((behind + 2 * (at(-s) - P)) ** 2).sum(axis=0)
        take_ahead = (bend_ahead <= bend_behind) | np.isnan(bend_behind)
    take_ahead &= np.isfinite(ahead[0])  # unknown ahead: behind, or NaN if that is too
    return np.where(take_ahead, ahead, behind)


def close_neighbours(values: np.ndarray, threshold) -> np.ndarray:
    """(H, W) uint8: how many of each cell's 8 neighbours lie within ``threshold`` of
    its value (a scalar or an (H, W) array); unknown (NaN) neighbours never do."""
    v = np.asarray(values, dtype=np.float32)
    padded = np.pad(v, 1, constant_values=np.nan)
    H, W = v.shape
    near = np.zeros(v.shape, np.uint8)
    with np.errstate(invalid="ignore"):
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if dr or dc:
                    nb = padded[1 + dr : 1 + dr + H, 1 + dc : 1 + dc + W]
                    near += np.abs(nb - v) <= threshold
    return near


def depth_outliers(
    depth: np.ndarray, *, rel: float = 0.03, jump: float = 1.0, support: int = 2
) -> np.ndarray:
    """(H, W) bool: gross matching errors, pixels with fewer than ``support`` of their
    8 neighbours within ``max(jump, rel * depth)`` metres of their depth.

    Such errors are isolated pixels tens of metres off. Left in, each one bends the
    smoothed depth that :func:`normal_z_image` differentiates over a few pixels around
    it, and with 2 % of them a facade's normals turn up and its points pass for a top
    surface; each also reads as a jump (:func:`depth_jumps`) to its neighbours. A
    surface's pixels, even at a roof's corner or a crown's rim, have neighbours on the
    same surface; a median filter would shave those off.
    """
    d = np.asarray(depth, dtype=np.float32)
    return np.isfinite(d) & (close_neighbours(d, np.maximum(jump, rel * d)) < support)


def depth_jumps(depth: np.ndarray, *, k: int = 3, rel: float = 0.03, jump: float = 1.0):
    """(H, W) bool: pixels within ``k`` pixels of a depth discontinuity.

    Dense matching rounds depth edges into ramps whose points float between the two
    surfaces; a pixel is near a jump when the depths ``k`` pixels to either side (along
    rows or columns) differ by more than ``max(jump, rel * depth)``, or, where one side
    is unknown, when the known side is more than half that from the pixel. Steep roofs
    seen from above change by far less.
    """
    d = np.asarray(depth, dtype=np.float32)
    near = np.zeros(d.shape, bool)
    with np.errstate(invalid="ignore"):
        thr = np.maximum(jump, rel * d)
        for axis in (0, 1):
            across, one_sided = _across_jump(
                d, np.roll(d, k, axis=axis), np.roll(d, -k, axis=axis), thr
            )
            near |= across | one_sided
    return near


def _across_jump(z, before, after, thr) -> tuple[np.ndarray, np.ndarray]:
    """Whether depths ``z`` lie within reach of a jump larger than ``thr``, given the
    depths ``before`` and ``after`` them along an axis (same shapes): with both sides
    known (``across``), or with one (``one_sided``: beside a hole, an occlusion's often,
    the pixel stands for the middle of the ramp, half the jump from the known side)."""
    both = np.isfinite(before) & np.isfinite(after)
    across = both & (np.abs(before - after) > thr)
    one_sided = ~both & (2 * np.fmax(np.abs(z - before), np.abs(z - after)) > thr)
    return across, one_sided


# (axis, sign) of each side a pixel's nearer surface can lie on (:func:`near_side`): the
# side's pixels are ``np.roll(image, sign * k, axis)``'s, ``k`` pixels up, down, left, right
NEAR_SIDES = ((0, 1), (0, -1), (1, 1), (1, -1))
# of the jump threshold; chosen on small seed 0 (DSM RMSE off the height jumps 0.439, 0.435
# and 0.473 m at 0.05, 0.1, 0.25; 0.460 m before) and checked on seeds 1 and 2
NEAR_SIDE_AGREE = 0.1


def near_side(
    depth: np.ndarray, jumps: np.ndarray, *, k: int = 3, rel: float = 0.03, jump: float = 1.0,
    agree: float = NEAR_SIDE_AGREE,
) -> np.ndarray:  # fmt: skip
    """(H, W) int8: for a pixel near a depth jump (``jumps``: :func:`depth_jumps` of
    ``depth`` with the same ``k``, ``rel`` and ``jump``) that lies on the jump's nearer
    surface, not on the ramp between the two, 1 + the index in :data:`NEAR_SIDES` of the
    side that surface lies on; 0 elsewhere.

    Dense matching rounds a jump into a ramp a few pixels wide, so :func:`depth_jumps`
    drops every pixel within ``k`` of it, and with them the rim of each roof: beside a
    tall building whose ground is hidden, no view kept the roof's outer 0.5-0.75 m
    (``small`` seed 0: a 72 m tower's north rim, 3 cells wide, fused as unknown). A pixel
    is on the nearer surface when, across every axis along which it is near a jump, the
    jump's nearer side is known two-sided and the pixel's depth lies on the line through
    that side's depths ``k`` and ``2 k`` pixels away, within ``agree`` x the jump
    threshold ``max(jump, rel * depth)``: on the ramp it is off that line by a share of
    the jump itself. Its normal is then read ``2 k`` pixels in on that side
    (:func:`normals_from_near_side`), since the one at the pixel is smoothed across the
    jump. A pixel whose normal would be read past the image keeps its jump.
    """
    d = np.asarray(depth, dtype=np.float32)
    code = np.zeros(d.shape, np.int8)
    rows, cols = np.nonzero(jumps)  # only those: a few percent of the pixels
    at = (rows, cols)
    z = d[at]
    thr = np.maximum(jump, rel * z)
    placed = np.zeros(len(z), np.int8)
    on_side = np.ones(len(z), bool)

    def depth_at(axis: int, offset: int) -> np.ndarray:  # np.roll's: wraps at the edges
        if axis == 0:
            return d[(rows + offset) % d.shape[0], cols]
        return d[rows, (cols + offset) % d.shape[1]]

    with np.errstate(invalid="ignore"):
        for axis in (0, 1):
            across, one_sided = _across_jump(z, depth_at(axis, -k), depth_at(axis, k), thr)
            continues = np.zeros(len(z), bool)
            for i, (ax, sign) in enumerate(NEAR_SIDES):
                if ax != axis:
                    continue
                n1, n2 = depth_at(axis, -sign * k), depth_at(axis, -2 * sign * k)
                far = depth_at(axis, sign * k)
                source = at[axis] - 2 * sign * k  # where its normal is read
                inside = (source >= 0) & (source < d.shape[axis])
                ok = across & inside & (n1 < far) & (np.abs(z - (2 * n1 - n2)) <= agree * thr)
                placed = np.where(ok & (placed == 0), np.int8(i + 1), placed)
                continues |= ok
            on_side &= ~(across | one_sided) | continues
    code[at] = np.where(on_side, placed, np.int8(0))
    return code


def normals_from_near_side(nz: np.ndarray, side: np.ndarray, k: int = 3) -> np.ndarray:
    """``nz`` ((H, W), of :func:`normal_z_image`) with each pixel that :func:`near_side`
    puts on a jump's nearer surface given the normal ``2 k`` pixels in on that side
    (``side``: its codes, on the same window)."""
    out = nz.copy()
    for i, (axis, sign) in enumerate(NEAR_SIDES):
        on = side == i + 1
        if on.any():
            out[on] = np.roll(nz, sign * 2 * k, axis=axis)[on]
    return out


# pixels looked across a hole for its far side (:func:`behind_occlusions`): past the
# sample's occlusion holes (7 pixels) and the jump's reach. On small seeds 0-2, with a first
# version (lone unknown pixels filled first), DSM RMSE off the height jumps 0.358, 0.404,
# 0.413 m at 8; 0.346, 0.399, 0.402 m at 12; 0.346, 0.390, 0.407 m at 24, which is kept, the
# widest: a real occlusion's hole is as wide as its parallax
OCCLUSION_REACH = 24


def behind_occlusions(
    depth: np.ndarray, *, k: int = 3, reach: int = OCCLUSION_REACH, rel: float = 0.03,
    jump: float = 1.0,
) -> np.ndarray:  # fmt: skip
    """(H, W) bool: pixels within ``k`` pixels of a hole, along a row or column, beyond
    which the first known depth, within ``reach`` pixels, is nearer by more than
    ``max(jump, rel * depth)``: the background beside an occlusion.

    Stereo matching cannot match the background that one image of the pair sees and the
    other does not, so a hole opens beside a nearer surface's edge, and the pixels of
    the background beside it are the far end of the ramp that matching rounds the jump
    into. Their jump is not seen (:func:`depth_jumps` compares a pixel with what lies
    ``k`` pixels away, the hole), and their normal is read across the hole, into the
    smoothed depth carried over it (:func:`normal_z_image`): on ``small`` dev seed 6 a
    wall beside a hole, seen by two oblique views, had normals of z 0.9-1.0 and passed
    for a roof 3 m below the true one, over a 1 m strip of ground that no other view
    saw. Reading their normal away from the hole instead did not help (seed 0's DSM RMSE
    off the height jumps 0.367 -> 0.387 m): their depth is the ramp's. The nearer side of
    the occlusion is not flagged (across its hole lies a farther surface), nor is a
    surface beside a lone unknown pixel. :func:`observe` does not trust the flagged
    pixels; what a view sees past still counts them
    (:func:`~fusion.hidden_ceiling.trusted_depth`).
    """
    d = np.asarray(depth, dtype=np.float32)
    unknown = ~np.isfinite(d)
    out = np.zeros(d.shape, bool)
    for axis in (0, 1):
        n = d.shape[axis]
        # a lone unknown pixel along the axis (a dropped gross error, mostly) has the
        # pixel's own surface beyond it: only runs of two or more are looked across
        run = unknown & (shifted(unknown, 1, axis) | shifted(unknown, -1, axis))
        for sign in (1, -1):
            hole_near = np.zeros(d.shape, bool)
            for o in range(1, k + 1):
                hole_near |= shifted(run, sign * o, axis)
            rows, cols = np.nonzero(hole_near & ~unknown)  # a few percent of the pixels
            at = rows if axis == 0 else cols
            first = np.full(len(at), reach + 1)  # offset of the hole's first pixel
            beyond = np.full(len(at), np.nan, np.float32)
            for o in range(1, reach + 1):
                q = at + sign * o
                inside = (q >= 0) & (q < n)
                q = np.clip(q, 0, n - 1)
                v = np.where(inside, d[q, cols] if axis == 0 else d[rows, q], np.nan)
                known = np.isfinite(v)
                first = np.where(~known & (first > reach), o, first)
                take = known & (first < o) & np.isnan(beyond)
                beyond[take] = v[take]
            z = d[rows, cols]
            with np.errstate(invalid="ignore"):
                nearer = (first <= k) & (beyond < z - np.maximum(jump, rel * z))
            out[rows[nearer], cols[nearer]] = True
    return out


def height_weights(center: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """(N,) float32 weight of each point's height in its cell's median: ``cos**2`` of
    its ray's angle from the vertical.

    A ray's error moves its point by ``sin`` of that angle horizontally, and beside a
    wall a point moved into the next cell is a wall's height wrong; an oblique ray also
    sees under crowns the top surface hides. The weight favours the steep rays without
    silencing the oblique ones (45 degrees: half). On ``small``, the square beat the
    depth-error model ``depth**2 |u_z| / (u . axis)``, which trusts grazing rays most
    (DSM RMSE 1.47 against 2.17 m, unweighted 1.53 m), and the fourth power (1.45 m
    but 0.047 m median error against 0.044 m).

    Parameters
    ----------
    center : (3,) camera centre, metres
    xyz : (N, 3) world points, metres
    """
    # an axis at a time (NumPy's loops run along columns, not triples), summed in the
    # order np.einsum("ij,ij->i") sums them, so that the weights stay what they were
    x, y, z = (xyz[:, k] - center[k] for k in range(3))
    z2 = z * z
    cos2 = z2 / np.maximum((x * x + z2) + y * y, 1e-18)
    return cos2.astype(np.float32)


def lift_depth(
    camera: Camera, depth: np.ndarray, rays: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """World points of every pixel with a depth.

    ``rays``, the (H*W, 3) directions of :meth:`Camera.pixel_grid_rays`, spares
    computing them again for a caller that has them.

    Returns
    -------
    pixels : (N,) int64 flat pixel indices; xyz : (N, 3) float64 world points.
    """
    valid = np.isfinite(depth) & (depth > 0)
    pixels = np.flatnonzero(valid)
    d = depth.ravel()[pixels]
    return pixels, lift_pixels(camera, pixels, d, depth.shape[1], rays)


def lift_pixels(
    camera: Camera, pixels: np.ndarray, depth: np.ndarray, width: int,
    rays: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """(N, 3) float64 world points of the flat ``pixels`` (N,) (row * ``width`` + column)
    at z-depths ``depth`` (N,), metres; ``rays`` as for :func:`lift_depth`."""
    if rays is None:
        v, u = np.divmod(pixels, width)
        _, dirs = camera.pixel_rays(np.column_stack([u, v]).astype(np.float64))
    else:
        dirs = rays[pixels]
    d = depth.astype(np.float64)
    xyz = np.empty((len(pixels), 3))
    for k in range(3):  # an axis at a time: NumPy's loops run along columns, not triples
        np.multiply(dirs[:, k], d, out=xyz[:, k])
        xyz[:, k] += camera.center[k]
    return xyz


def nearest_depth(cells: np.ndarray, depth: np.ndarray, top: np.ndarray, n_cells: int):
    """(N,) the nearest depth of each observation's cell, over the ``top`` (non-steep)
    observations of the cell, or over all of them in a cell with none.

    Parameters
    ----------
    cells : (N,) int64 flat cell indices
    depth : (N,) float z-depths, metres
    top : (N,) bool
    n_cells : int
    """
    # one pass: steep points count only in cells without a top point
    offset = np.float32(2 * (float(depth.max()) + 1.0)) if len(depth) else np.float32(1.0)
    key = np.where(top, depth, depth + offset).astype(np.float32)
    nearest = np.full(n_cells, np.inf, np.float32)
    np.minimum.at(nearest, cells, key)
    nearest = np.where(nearest >= offset, nearest - offset, nearest)
    return nearest[cells]


def visibility_groups(
    cells: np.ndarray, quarter: np.ndarray, top: np.ndarray, n_cells: int
) -> tuple[np.ndarray, int]:
    """The groups of one view's observations within which the nearest surface hides
    what lies behind it: its cell, or its quarter of the cell where the view sees a
    facade in the cell.

    A cell at a wall's foot holds both the roof's edge and the ground before the wall,
    and a view facing the wall sees both; judged per cell, the nearer roof hid that
    ground and the roofs grew outward (small seed 0: 1,100 ground cells beside walls
    took a roof's height, 563 roof cells the ground's; judged per quarter, 544 and
    817). Elsewhere a quarter is too small: the ground under a crown's edge, seen past
    it, would count as seen.

    Parameters
    ----------
    cells : (N,) int64 flat cell indices
    quarter : (N,) int quarter of the cell (0-3) each observation lies in
    top : (N,) bool, observations of non-steep surfaces (the others: facades)
    n_cells : int

    Returns
    -------
    groups : (N,) int64 group index; n_groups : int
    """
    facade = np.bincount(cells[~top], minlength=n_cells) > 0
    rank = np.cumsum(facade) - 1
    groups = np.where(facade[cells], n_cells + 4 * rank[cells] + quarter, cells)
    return groups.astype(np.int64), n_cells + 4 * int(facade.sum())


# pixels the normals read around a pixel in :func:`observe`: OpenCV's Gaussian kernel of
# sigma 1.5 reaches 6, the one-sided differences 6 (:func:`_one_sided_difference`), and a
# pixel on a jump's nearer surface reads its normal 6 pixels in
# (:func:`normals_from_near_side`)
OBSERVE_MARGIN = 6 + 6 + 6
COLUMN_BLOCK = 64  # float32 columns: four AVX-512 vectors
WINDOW_BAND = 32  # image rows whose rays grid_window holds at once: 0.6 MB at 1024 columns


def grid_window(
    depth: np.ndarray, camera: Camera, grid: Grid, margin: int
) -> tuple[slice, slice] | None:
    """The rows and columns of a view that can see the grid: the bounding box of the
    pixels whose depth puts their point within a cell of the grid, widened by ``margin``
    pixels (clipped to the image); None where no pixel does.

    An oblique view sees far beyond the grid (on ``small``, 37 % of the views' pixels
    land in it); the image filters and the lifting need only this window, and a filter
    that reads ``margin`` pixels around a pixel gives inside it what it gives on the
    whole image.

    Parameters
    ----------
    depth : (H, W) float z-depth, metres, NaN unknown
    camera : Camera
    grid : Grid
    margin : int
    """
    H, W = depth.shape
    x0, y0, x1, y1 = grid.bounds
    slack = grid.gsd  # the window may be larger than needed, never smaller
    cx, cy = camera.center[:2]
    near = np.empty((H, W), bool)
    # a band of rows at a time: the whole image's (H*W, 3) rays would be written to
    # memory and read back, most of this function's time
    for r0 in range(0, H, WINDOW_BAND):
        band = slice(r0, min(r0 + WINDOW_BAND, H))
        _, rays = camera.pixel_grid_rays(window=(band, slice(None)))
        d = depth[band].ravel().astype(np.float64)
        with np.errstate(invalid="ignore"):  # NaN depths compare False
            x = rays[:, 0] * d
            y = rays[:, 1] * d
            inside = ((x >= x0 - cx - slack) & (x <= x1 - cx + slack)
                      & (y >= y0 - cy - slack) & (y <= y1 - cy + slack))  # fmt: skip
        near[band] = inside.reshape(-1, W)
    rows, cols = np.flatnonzero(near.any(axis=1)), np.flatnonzero(near.any(axis=0))
    if not len(rows):
        return None
    # columns in whole blocks of COLUMN_BLOCK from the image's left edge: OpenCV's
    # filters treat the columns past a row's last whole SIMD vector apart, and rounded
    # differently there a window's last columns would not match the whole image's
    c0 = max(cols[0] - margin, 0) // COLUMN_BLOCK * COLUMN_BLOCK
    c1 = min(-(-(cols[-1] + 1 + margin) // COLUMN_BLOCK) * COLUMN_BLOCK, W)
    return slice(max(rows[0] - margin, 0), min(rows[-1] + 1 + margin, H)), slice(c0, c1)


def window_pixels(window: tuple[slice, slice], pixels: np.ndarray, width: int) -> np.ndarray:
    """(N,) int64 flat indices in the whole image (of ``width`` columns) of ``pixels``,
    flat indices in ``window``."""
    rows, cols = window
    v, u = np.divmod(pixels, cols.stop - cols.start)
    return (v + rows.start) * width + (u + cols.start)


def in_window(window: tuple[slice, slice], shape: tuple[int, int], pixels, xyz):
    """The ``pixels`` (flat indices in an image of ``shape``) inside ``window`` as flat
    indices in it, with their ``xyz``."""
    rows, cols = window
    v, u = np.divmod(pixels, shape[1])
    inside = (v >= rows.start) & (v < rows.stop) & (u >= cols.start) & (u < cols.stop)
    local = (v[inside] - rows.start) * (cols.stop - cols.start) + (u[inside] - cols.start)
    return local, xyz[inside]


def screened_depth(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A view's depth map (H, W) with its gross matching errors NaN
    (:func:`depth_outliers`), the pixels near its jumps (:func:`depth_jumps`) and those
    of them on a jump's nearer surface (:func:`near_side`), each (H, W)."""
    depth = np.where(depth_outliers(depth), np.float32(np.nan), depth)
    jumps = depth_jumps(depth)
    return depth, jumps, near_side(depth, jumps)


def observe(
    camera: Camera, depth: np.ndarray, grid: Grid, *, tolerance: float = 1.0
) -> ViewObservations:
    """The observations a view makes of the ortho grid.

    Parameters
    ----------
    camera : Camera
    depth : (H, W) float
        z-depth map, metres, NaN unknown.
    grid : Grid
        The ortho grid.
    tolerance : float
        Depth band behind the nearest point of a cell that still counts as the same
        surface, metres (absorbs depth noise and slanted surfaces).
    """
    H, W = depth.shape
    # on the whole image: np.roll compares the pixels by its edges with its far side
    depth, jumps, side = screened_depth(depth)
    # not trusted as a surface, but its depth still bounds what the view sees past
    # (:func:`~fusion.hidden_ceiling.trusted_depth`): the ray did pass the occluder
    behind = behind_occlusions(depth)
    window = grid_window(depth, camera, grid, OBSERVE_MARGIN)
    if window is None:
        none = np.zeros(0, np.int64)
        return ViewObservations(none, none, np.zeros((0, 3)), np.zeros(0, np.float32),
                                np.zeros(0, bool), np.zeros(0, np.float32), np.zeros(0, bool),
                                np.zeros(0, np.float32))  # fmt: skip
    depth, jumps, side, behind = depth[window], jumps[window], side[window], behind[window]
    _, rays = camera.pixel_grid_rays(window=window)
    pixels, xyz = lift_depth(camera, depth, rays)
    # indices of half cells: the cell is the index // 2, the quarter of it the index % 2
    r, c = grid.world_to_cell(xyz[:, 0], xyz[:, 1])
    hr, hc = np.floor(2 * r + 1).astype(np.int64), np.floor(2 * c + 1).astype(np.int64)
    inside = grid.contains(hr // 2, hc // 2)
    pixels, xyz, hr, hc = pixels[inside], xyz[inside], hr[inside], hc[inside]
    cells = (hr // 2) * grid.width + hc // 2
    d = depth.ravel()[pixels]
    # a pixel on a jump's nearer surface takes that surface's normal, and is trusted
    # unless that normal is unknown
    nz_image = normals_from_near_side(normal_z_image(camera, depth, rays=rays), side)
    jumps = (jumps & ~((side > 0) & np.isfinite(nz_image))) | behind
    nz = np.nan_to_num(nz_image.ravel()[pixels], nan=1.0)
    top = nz > STEEP_NORMAL_Z
    groups, n_groups = visibility_groups(
        cells, 2 * (hr % 2) + hc % 2, top, grid.width * grid.height
    )
    visible = d <= nearest_depth(groups, d, top, n_groups) + tolerance
    near_jump = jumps.ravel()[pixels]
    weight = height_weights(camera.center, xyz)
    pixels = window_pixels(window, pixels, W)
    return ViewObservations(pixels, cells, xyz, d, visible, nz, near_jump, weight)

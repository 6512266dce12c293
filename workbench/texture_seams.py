"""Texture seams (the voxel paper's eq. 5), measured the same way for any textured model.

What every view sees of points on a surface (:func:`view_samples`), and the seam cost of
a labelling of those points with views (:func:`seam_cost`): the voxel path stitches its
textures with it, and ``workbench compare`` recomputes it from a run's textured meshes
and the scene's views (:func:`recomputed_seam_costs`), for the run's texture and for
projective texture mapping on the same points.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from .camera import Camera, framing_cameras
from .errors import InputError
from .imageio import read_rgb
from .meshio import read_obj, texture_of
from .raycast import occluded

MISSING_LAB = 100.0  # Lab units: a seam through a vertex one of the two views cannot see
MIN_COS = 0.1  # views grazing a face more than this are no use to texture it


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) RGB 0-255 (any float or uint8) to CIE Lab (L 0-100), float32."""
    shape = rgb.shape
    flat = np.asarray(rgb, np.float32).reshape(-1, 1, 3) / 255.0
    return cv2.cvtColor(flat, cv2.COLOR_RGB2Lab).reshape(shape)


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample ``image`` (H, W, C) at pixel coordinates ``uv`` (N, 2) -> (N, C) float32."""
    if len(uv) == 0:
        return np.zeros((0, image.shape[2]), np.float32)
    n = len(uv)
    width = 4096  # remap's maps must stay under 32767 on each side
    rows = -(-n // width)
    m = np.zeros((rows * width, 2), np.float32)
    m[:n] = uv
    m = m.reshape(rows, width, 2)
    out = cv2.remap(image, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * width, -1)[:n].astype(np.float32)


@dataclass
class ViewSamples:
    """What every view sees of every graph vertex.

    Attributes
    ----------
    visible : (V, K) bool
        The view faces the vertex, has it in frame and nothing hides it.
    facing : (V, K) float
        Cosine between the vertex normal and the direction to the view.
    lab : (V, K, 3) float32
        CIE Lab colour (valid where visible).
    rgb : (V, K, 3) uint8
    """

    visible: np.ndarray
    facing: np.ndarray
    lab: np.ndarray
    rgb: np.ndarray


def view_samples(
    positions: np.ndarray,
    normals: np.ndarray,
    cameras: list[Camera],
    images,
    occluders=None,
    views: list[int] | None = None,
) -> ViewSamples:
    """Visibility (ray casting against ``occluders``) and colour of every vertex in every
    view, or in ``views`` only: then column j of the arrays is view ``views[j]``.

    Parameters
    ----------
    positions, normals : (V, 3)
    cameras : list of Camera
    images
        Anything with ``rgb_samples(k, uv)``: view ``k``'s RGB (0-255) at pixel
        coordinates ``uv`` (N, 2) -> (N, 3) float.
    occluders : workbench.raycast.RayScene, optional
        Every proxy of the scene.
    """
    views = list(range(len(cameras))) if views is None else list(views)
    sights = [_sighting(positions, normals, cameras[k], k, images, occluders) for k in views]
    return _samples(len(positions), sights)


def seen_views(
    positions: np.ndarray,
    normals: np.ndarray,
    cameras: list[Camera],
    images,
    occluders=None,
    views: list[int] | None = None,
) -> tuple[list[int], ViewSamples]:
    """:func:`view_samples` of the views (of ``views``) that see at least one vertex,
    and those views: a view that sees nothing is no label of a cut, and would only cost
    time. When no view sees any vertex, every view is kept."""
    views = list(range(len(cameras))) if views is None else list(views)
    sights = [_sighting(positions, normals, cameras[k], k, images, occluders) for k in views]
    kept = [j for j, (sel, _, _) in enumerate(sights) if len(sel)] or list(range(len(views)))
    return [views[j] for j in kept], _samples(len(positions), [sights[j] for j in kept])


def framed(
    positions: np.ndarray, normals: np.ndarray, cam: Camera
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vertices that face view ``cam`` by more than ``MIN_COS`` and lie in its frame,
    before any occlusion: their indices (N,) int, cosines (N,) float and pixel
    coordinates (N, 2)."""
    to_cam = cam.center - positions
    dist = np.linalg.norm(to_cam, axis=1)
    cos = np.einsum("ij,ij->i", to_cam, normals) / np.maximum(dist, 1e-9)
    sel = np.flatnonzero(cos > MIN_COS)
    uv, depth = cam.project(positions[sel])
    inside = (
        (depth > 0)
        & (uv[:, 0] >= 0)
        & (uv[:, 1] >= 0)
        & (uv[:, 0] <= cam.width - 1)
        & (uv[:, 1] <= cam.height - 1)
    )
    return sel[inside], cos[sel[inside]], uv[inside]


def hidden_from(occluders, positions: np.ndarray, normals: np.ndarray,
                centre: np.ndarray) -> np.ndarray:  # fmt: skip
    """(N,) bool: something of ``occluders`` lies between each vertex (lifted 5 cm off its
    surface along its normal, so that it does not hide itself) and the projection centre
    ``centre`` (3,) it is looked at from."""
    lifted = positions + 0.05 * normals
    return occluded(occluders, lifted, centre - lifted, tfar=1.0)


def _sighting(positions, normals, cam: Camera, k: int, images, occluders):
    """The vertices view ``k`` sees ((N,) int), their cosines to it ((N,) float) and their
    RGB there ((N, 3) float 0-255)."""
    sel, cos, uv = framed(positions, normals, cam)
    if occluders is not None and len(sel):
        hidden = hidden_from(occluders, positions[sel], normals[sel], cam.center)
        sel, cos, uv = sel[~hidden], cos[~hidden], uv[~hidden]
    if not len(sel):
        return sel, cos, np.zeros((0, 3), np.float32)
    return sel, cos, images.rgb_samples(k, uv)


def _samples(v: int, sights: list) -> ViewSamples:
    """ViewSamples of ``v`` vertices from one :func:`_sighting` per view.

    Stored view by view (each view's column contiguous), so that filling a view and
    reading one view for every vertex, as the cuts do, run along memory; the arrays are
    (V, K, ...) views of that storage."""
    n = len(sights)
    visible = np.zeros((n, v), bool)
    facing = np.zeros((n, v), np.float32)
    lab = np.zeros((n, v, 3), np.float32)
    rgb = np.zeros((n, v, 3), np.uint8)
    for j, (sel, cos, colours) in enumerate(sights):
        if not len(sel):
            continue
        visible[j, sel] = True
        facing[j, sel] = cos
        rgb[j, sel] = np.clip(np.round(colours), 0, 255).astype(np.uint8)
        lab[j, sel] = rgb_to_lab(colours)
    return ViewSamples(visible.T, facing.T, lab.transpose(1, 0, 2), rgb.transpose(1, 0, 2))


def _view_differences(
    edges: np.ndarray, src: np.ndarray, dst: np.ndarray, samples: ViewSamples
) -> tuple[np.ndarray, np.ndarray]:
    """||P1(x) - P2(x)|| in CIE Lab at both ends x of each edge, views ``src`` and ``dst``
    (each (E,)), and whether both views see x: two (E, 2) arrays."""
    d = np.empty((len(edges), 2))
    ok = np.empty((len(edges), 2), bool)
    for end in (0, 1):
        x = edges[:, end]
        ok[:, end] = samples.visible[x, src] & samples.visible[x, dst]
        d[:, end] = np.linalg.norm(samples.lab[x, src] - samples.lab[x, dst], axis=1)
    return d, ok


def seam_costs(
    edges: np.ndarray, src: np.ndarray, dst: np.ndarray, samples: ViewSamples
) -> np.ndarray:
    """C(s, t) of eq. 5 for each edge (s, t) between views ``src`` and ``dst`` (each (E,)):
    ||P1(s) - P2(s)|| + ||P1(t) - P2(t)|| in CIE Lab. A term a view cannot see costs
    ``MISSING_LAB``."""
    return seam_terms(edges[:, 0], src, dst, samples) + seam_terms(edges[:, 1], src, dst, samples)


def seam_terms(x: np.ndarray, src, dst, samples: ViewSamples) -> np.ndarray:
    """(N,) float64 one vertex's term of C in eq. 5: ||P_src(x) - P_dst(x)|| in CIE Lab
    at the vertices ``x`` (N,), ``MISSING_LAB`` where either view does not see x.
    ``src`` and ``dst`` are views, (N,) or one for all; the term is symmetric in them."""
    ok = samples.visible[x, src] & samples.visible[x, dst]
    d = np.linalg.norm(samples.lab[x, src] - samples.lab[x, dst], axis=1).astype(np.float64)
    return np.where(ok, d, MISSING_LAB)


def seam_cost(edges: np.ndarray, labels: np.ndarray, samples: ViewSamples) -> tuple[float, int]:
    """The texture's seam cost: the energy of eq. 5 per edge of the surface graph.

    An edge whose two vertices take different views costs the mean Lab difference of
    those two views at its two vertices, over the views that see them (eq. 5 halved); a
    seam whose two sides no view shares (neither of its views sees both vertices) is as
    visible as a seam can be and costs ``MISSING_LAB``; an edge inside one view's patch
    costs nothing. The sum is divided by all the edges, not by the seams: a labelling
    with fewer seams is the better texture, though what seams it keeps may be the hard
    ones. Returns (cost, number of seam edges)."""
    a, b = labels[edges[:, 0]], labels[edges[:, 1]]
    seam = (a != b) & (a >= 0) & (b >= 0)
    if not seam.any():
        return 0.0, 0
    d, ok = _view_differences(edges[seam], a[seam], b[seam], samples)
    counts = ok.sum(axis=1)
    shared = np.where(ok, d, 0.0).sum(axis=1) / np.maximum(counts, 1)
    per_edge = np.where(counts > 0, shared, MISSING_LAB)
    return float(per_edge.sum() / len(edges)), int(seam.sum())


class SceneImages:
    """The views' images, read when first sampled and kept while they fit in a memory
    budget, the least recently used going first: a city's flight has hundreds of views, of
    which one building needs a few dozen, and its neighbours mostly the same ones.

    Parameters
    ----------
    views : list of View
    budget_mb : float
        Memory for the images kept (at least the last one read is kept).
    """

    def __init__(self, views: list, budget_mb: float = 1024.0):
        self.views = views
        self._rgb: OrderedDict[int, np.ndarray] = OrderedDict()
        self._budget = budget_mb * 2**20
        self._bytes = 0

    def rgb(self, k: int) -> np.ndarray:
        """(H, W, 3) uint8 image of view ``k``."""
        if k in self._rgb:
            self._rgb.move_to_end(k)
            return self._rgb[k]
        img = self._rgb[k] = self.views[k].read_image()
        self._bytes += img.nbytes
        while self._bytes > self._budget and len(self._rgb) > 1:
            _, old = self._rgb.popitem(last=False)
            self._bytes -= old.nbytes
        return img

    def __getstate__(self):  # sent to a worker without the images read so far
        return {**self.__dict__, "_rgb": OrderedDict(), "_bytes": 0}

    def rgb_samples(self, k: int, uv: np.ndarray) -> np.ndarray:
        """RGB of view ``k`` at ``uv`` (N, 2), bilinear -> (N, 3) float32 0-255."""
        return bilinear(self.rgb(k), uv)


@dataclass
class SurfaceTexels:
    """Points on a textured mesh, about ``spacing`` apart, and what its texture shows
    there.

    positions, normals : (N, 3) world metres and unit outward normals; triangle : (N,)
    the triangle each lies on; rgb : (N, 3) float the texture's colour; edges : (E, 2)
    pairs of points within 1.5 spacings (across triangle borders too: the seams of the
    texture's charts are seams like any other).
    """

    positions: np.ndarray
    normals: np.ndarray
    triangle: np.ndarray
    rgb: np.ndarray
    edges: np.ndarray


def surface_texels(
    vertices: np.ndarray,
    triangles: np.ndarray,
    uvs: np.ndarray,
    image: np.ndarray,
    spacing: float,
) -> SurfaceTexels:
    """Points on a square grid of ``spacing`` in the plane of every triangle (its
    centroid for a triangle smaller than a grid cell), with the texture's colour at each.
    Floors (facing down) and zero-area triangles are left out: no view sees them.

    Parameters
    ----------
    vertices : (V, 3), triangles : (T, 3)
        The mesh, world metres.
    uvs : (T, 3, 2)
        Texture coordinates of the corners, u right and v up, 0-1.
    image : (h, w, 3) uint8
        The texture.
    """
    p = vertices[triangles]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    keep = (area2 > 1e-9) & (cross[:, 2] > -0.9 * area2)
    bary, tri = [], []
    for t in np.flatnonzero(keep):
        e1 = p[t, 1] - p[t, 0]
        u = e1 / np.linalg.norm(e1)
        v = np.cross(cross[t] / area2[t], u)
        q = (p[t] - p[t, 0]) @ np.column_stack([u, v])  # (3, 2) corners in the plane
        lo, hi = q.min(axis=0), q.max(axis=0)
        gu = np.arange(lo[0] + spacing / 2, hi[0], spacing)
        gv = np.arange(lo[1] + spacing / 2, hi[1], spacing)
        g = np.stack(np.meshgrid(gu, gv, indexing="ij"), -1).reshape(-1, 2)
        # barycentric coordinates of the grid points; inside where all are >= 0
        m = np.column_stack([q[1] - q[0], q[2] - q[0]])
        lam = np.linalg.solve(m, (g - q[0]).T).T if len(g) else np.zeros((0, 2))
        b = np.column_stack([1 - lam.sum(axis=1), lam])
        b = b[(b >= -1e-9).all(axis=1)]
        if not len(b):
            b = np.full((1, 3), 1 / 3)
        bary.append(b)
        tri.append(np.full(len(b), t))
    if not bary:
        z = np.zeros((0, 3))
        return SurfaceTexels(z, z, np.zeros(0, int), z, np.zeros((0, 2), int))
    bary, tri = np.concatenate(bary), np.concatenate(tri)
    positions = np.einsum("nc,ncd->nd", bary, p[tri])
    uv = np.einsum("nc,ncd->nd", bary, uvs[tri])
    h, w = image.shape[:2]
    rgb = bilinear(image, np.column_stack([uv[:, 0] * w - 0.5, (1.0 - uv[:, 1]) * h - 0.5]))
    edges = cKDTree(positions).query_pairs(1.5 * spacing, output_type="ndarray")
    normals = cross[tri] / area2[tri, None]
    return SurfaceTexels(positions, normals, tri, rgb, edges.reshape(-1, 2))


def source_views(
    texture_rgb: np.ndarray, samples: ViewSamples, edges: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The view each point's texture was taken from: among the views that see the point,
    the one whose colours over the point and its neighbours (``edges``) are nearest the
    texture's (summed CIE Lab distances; a neighbour the view does not see counts
    ``MISSING_LAB``). Matched over a neighbourhood, two views that agree about one point
    do not make its source flip from point to point. Returns (N,) view index (-1 where
    no view sees the point) and (N,) the point's own Lab distance to that view (NaN
    there)."""
    d = np.linalg.norm(samples.lab - rgb_to_lab(texture_rgb)[:, None, :], axis=2)
    d = np.where(samples.visible, d, MISSING_LAB)
    n = len(d)
    i, j = edges[:, 0], edges[:, 1]
    near = sparse.coo_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(n, n))
    total = d + near.tocsr() @ d
    best = np.argmin(np.where(samples.visible, total, np.inf), axis=1)
    seen = samples.visible.any(axis=1)
    dist = d[np.arange(n), best]
    return np.where(seen, best, -1), np.where(seen, dist, np.nan)


def projective_views(
    texels: SurfaceTexels, centres: np.ndarray, samples: ViewSamples, patch_m: float
) -> np.ndarray:
    """Projective texture mapping on the same points: every patch of ``patch_m`` metres
    of a triangle (the voxel paper's voxel faces) from the view that faces it best
    (the highest mean cosine between its normal and the direction to the view, counting
    -1 where the view does not see a point), each point from its own best view where
    the patch's does not see it. Returns (N,) view index, -1 where no view sees it."""
    to_view = centres[None, :, :] - texels.positions[:, None, :]
    to_view /= np.linalg.norm(to_view, axis=2, keepdims=True)
    facing = np.einsum("nkc,nc->nk", to_view, texels.normals)
    score = np.where(samples.visible, facing, -1.0)
    cell = np.floor(texels.positions / patch_m).astype(np.int64)
    key = np.column_stack([texels.triangle, cell])
    _, patch = np.unique(key, axis=0, return_inverse=True)
    patch = patch.ravel()
    total = np.zeros((patch.max() + 1, score.shape[1]))
    np.add.at(total, patch, score)
    chosen = np.argmax(total, axis=1)[patch]
    own = np.argmax(np.where(samples.visible, facing, -np.inf), axis=1)
    n = np.arange(len(chosen))
    labels = np.where(samples.visible[n, chosen], chosen, own)
    return np.where(samples.visible.any(axis=1), labels, -1)


@dataclass
class TexturedBuilding:
    """A building's textured mesh as written: vertices (V, 3), triangles (T, 3), uvs
    (T, 3, 2) and the texture image (h, w, 3) uint8."""

    vertices: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray
    image: np.ndarray


def read_textured_building(obj_path: Path) -> TexturedBuilding | None:
    """A building's OBJ (:func:`~workbench.meshio.read_obj`, double precision) with its
    texture (the ``map_Kd`` of its ``.mtl``), None when it has no texture."""
    image_path = texture_of(obj_path)
    if image_path is None:
        return None
    vertices, triangles, uvs = read_obj(obj_path)
    if not len(triangles):
        return None
    if uvs is None:
        raise InputError(obj_path, "f", "a face without texture coordinates")
    return TexturedBuilding(vertices, triangles, uvs, read_rgb(image_path))


def recomputed_seam_costs(
    buildings: Iterable[TexturedBuilding],
    cameras: list[Camera],
    images,
    occluders=None,
    spacing: float = 0.5,
    patch_m: float = 1.0,
) -> dict:
    """The seam cost (:func:`seam_cost`) of a run's textures and of projective texture
    mapping, measured on the same points of its meshes with the same views.

    Which view a texture point came from is not written in the model: it is the view
    whose colour there is nearest the texture's (:func:`source_views`; ``source_lab``
    reports how near, a few Lab units when the texture is the views' own colours).

    Returns
    -------
    dict with ``seam_cost`` and ``seam_cost_projective`` (the seam energy per point pair
    over all buildings), ``seam_pairs`` and ``seam_pairs_projective``, ``points``,
    ``pairs``, ``unseen_points`` and ``source_lab_median``.
    """
    centres = np.array([c.center for c in cameras])
    energy = {"run": 0.0, "projective": 0.0}
    seams = {"run": 0, "projective": 0}
    points = pairs = unseen = 0
    match = []
    for b in buildings:
        tex = surface_texels(b.vertices, b.triangles, b.uvs, b.image, spacing)
        if not len(tex.edges):
            continue
        # the views that can see the building: the others would be columns of nothing
        # (if none can, one that sees nothing either)
        views = framing_cameras(cameras, b.vertices) or [0]
        samples = view_samples(tex.positions, tex.normals, cameras, images, occluders, views)
        labels, dist = source_views(tex.rgb, samples, tex.edges)
        for name, lab in (("run", labels), ("projective", projective_views(
                tex, centres[views], samples, patch_m))):  # fmt: skip
            cost, n_seams = seam_cost(tex.edges, lab, samples)
            energy[name] += cost * len(tex.edges)
            seams[name] += n_seams
        points += len(tex.positions)
        pairs += len(tex.edges)
        unseen += int((labels < 0).sum())
        match.append(dist[np.isfinite(dist)])
    if not pairs:
        return {}
    match = np.concatenate(match)
    return {
        "seam_cost": energy["run"] / pairs,
        "seam_cost_projective": energy["projective"] / pairs,
        "seam_pairs": seams["run"],
        "seam_pairs_projective": seams["projective"],
        "points": points,
        "pairs": pairs,
        "unseen_points": unseen,
        "source_lab_median": float(np.median(match)) if len(match) else None,
    }

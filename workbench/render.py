"""Pictures of meshes by ray casting (no OpenGL): the same viewpoints for every run."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from .camera import Camera, look_at_rotation
from .meshes import concatenate_meshes
from .raycast import cast, raycasting_scene

_LIGHT = np.array([-0.4, -0.5, 0.77])
_BACKGROUND = np.array([245, 245, 245], np.uint8)


def viewpoints(
    bounds: tuple[float, float, float, float],
    z_range: tuple[float, float],
    width: int = 640,
    height: int = 480,
) -> dict[str, Camera]:
    """Cameras that frame ``bounds`` (world xmin, ymin, xmax, ymax) from two sides.

    ``"south-west"`` and ``"north-east"`` look down at 40 degrees at the centre of the
    box spanned by the bounds and ``z_range`` (metres).
    """
    xmin, ymin, xmax, ymax = bounds
    centre = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, (z_range[0] + z_range[1]) / 2])
    radius = 0.5 * np.linalg.norm([xmax - xmin, ymax - ymin, z_range[1] - z_range[0]])
    f = 0.5 * width / np.tan(np.radians(25.0))  # 50 degree horizontal field of view
    K = np.array([[f, 0, width / 2 - 0.5], [0, f, height / 2 - 0.5], [0, 0, 1.0]])
    dist = 1.1 * radius / np.sin(np.radians(25.0))
    elev = np.radians(40.0)
    out = {}
    for name, az in (("south-west", 225.0), ("north-east", 45.0)):
        a = np.radians(az)
        toward = np.array([np.sin(a) * np.cos(elev), np.cos(a) * np.cos(elev), np.sin(elev)])
        c = centre + dist * toward
        R = look_at_rotation(-toward)
        out[name] = Camera(K, R, -R @ c, width, height)
    return out


def render_mesh(
    vertices: np.ndarray,
    triangles: np.ndarray,
    camera: Camera,
    face_colors: np.ndarray | None = None,
) -> np.ndarray:
    """Lambert-shaded picture of a mesh.

    Parameters
    ----------
    vertices : (V, 3) float
        World metres.
    triangles : (T, 3) int
    camera : Camera
    face_colors : (T, 3) uint8, optional
        Colour of each face (default light grey).

    Returns
    -------
    (height, width, 3) uint8 RGB; the background is light grey.
    """
    return render_meshes([(vertices, triangles, face_colors)], camera)


def render_meshes(meshes: Iterable[tuple], camera: Camera) -> np.ndarray:
    """:func:`render_mesh` of several meshes, one at a time (a scene too large to hold):
    each pixel shows the nearest hit of any. ``meshes`` gives (vertices, triangles,
    face colours or None) each."""
    img = np.tile(_BACKGROUND, (camera.height * camera.width, 1))
    origin = camera.center  # cast near the origin: float32 keeps its precision there
    centre, dirs = camera.pixel_grid_rays()
    nearest = np.full(len(dirs), np.inf)
    light = _LIGHT / np.linalg.norm(_LIGHT)
    for vertices, triangles, face_colors in meshes:
        if not len(triangles):
            continue
        hits = cast(raycasting_scene(vertices - origin, triangles), centre - origin, dirs)
        hit = hits.t < nearest
        nearest[hit] = hits.t[hit]
        colors = np.full((len(triangles), 3), 200, np.uint8) if face_colors is None else face_colors
        shade = 0.35 + 0.65 * np.abs(hits.normals[hit] @ light)
        img[hit] = np.clip(colors[hits.tri[hit]] * shade[:, None], 0, 255).astype(np.uint8)
    return img.reshape(camera.height, camera.width, 3)


# triangles cast at once when drawing the buildings: a whole-grid run's are one batch
RENDER_BATCH = 2_000_000


def render_buildings(buildings: Iterable, bounds, low: float | None = None) -> np.ndarray | None:
    """The buildings' meshes in grey from the south-west (:func:`viewpoints` of
    ``bounds``), or None without any. ``buildings`` is iterated twice (the height range,
    then the meshes a batch of at most ``RENDER_BATCH`` triangles at a time); ``low``: the
    ground's height, metres (default: the lowest vertex)."""
    z = [(m.vertices[:, 2].min(), m.vertices[:, 2].max()) for m in _meshes(buildings)]
    if not z:
        return None
    low = float(min(a for a, _ in z)) if low is None else low
    cam = viewpoints(bounds, (low, float(max(b for _, b in z))))["south-west"]

    meshes = ((m.vertices, m.triangles) for m in _meshes(buildings))
    return render_meshes((_grey(batch) for batch in triangle_batches(meshes)), cam)


def triangle_batches(parts: Iterable[tuple], limit: int | None = None,
                     image_bytes: int | None = None):  # fmt: skip
    """Lists of consecutive ``parts`` (tuples whose second item is a mesh's triangles),
    each closed once it holds ``limit`` (default ``RENDER_BATCH``) triangles or more, or,
    with ``image_bytes``, once the parts' images (their fourth item) take that many bytes
    or more."""
    limit = RENDER_BATCH if limit is None else limit
    batch, size, held = [], 0, 0
    for part in parts:
        batch.append(part)
        size += len(part[1])
        held += part[3].nbytes if image_bytes is not None else 0
        if size >= limit or (image_bytes is not None and held >= image_bytes):
            yield batch
            batch, size, held = [], 0, 0
    if batch:
        yield batch


def _meshes(buildings):
    return (b.mesh for b in buildings if len(b.mesh.triangles))


def _grey(meshes: list) -> tuple:
    V, T, _ = concatenate_meshes(meshes)
    return V, T, np.full((len(T), 3), 205, np.uint8)

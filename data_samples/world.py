"""The synthetic world as one triangle mesh with per-triangle attributes.

Every triangle knows its material, its class code (1 ground, 2 grass, 3 tree,
4 building), its building id (0 for none) and a texture axis, so that the
renderer can shade it and the truth rasters can be read off it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from modeling.shared.roof_envelope import building_mesh
from workbench.raycast import RayScene, raycasting_scene

from .layout import GROUND_CLASS, GROUND_MATERIALS, RURAL, TREE_HUES, Layout
from .roofs import wing_roof_faces
from .terrain import Terrain, graded_axis

# material kinds
K_ASPHALT, K_PAVEMENT, K_GRASS, K_SOIL, K_RURAL, K_ROOF, K_FACADE, K_TREE, K_TRUNK = range(9)
CLASS_TREE, CLASS_BUILDING = 3, 4

ROOF_PALETTE = np.array(
    [
        [0.42, 0.12, 0.08],  # red clay tiles
        [0.30, 0.10, 0.07],  # dark red tiles
        [0.10, 0.10, 0.11],  # dark slate, as dark as asphalt
        [0.085, 0.085, 0.09],  # tar, as dark as asphalt
        [0.30, 0.30, 0.30],  # grey concrete
        [0.45, 0.44, 0.40],  # light gravel
        [0.14, 0.22, 0.18],  # green metal
        [0.25, 0.16, 0.10],  # brown tiles
        # roofs a tree's colour would pass for: only their shape tells them apart
        [0.11, 0.17, 0.06],  # moss-green
        [0.20, 0.36, 0.30],  # copper-green (verdigris)
        [0.16, 0.22, 0.07],  # sedum
    ]
)
FACADE_PALETTE = np.array(
    [
        [0.62, 0.58, 0.50],
        [0.55, 0.35, 0.25],
        [0.70, 0.68, 0.62],
        [0.48, 0.45, 0.42],
        [0.60, 0.50, 0.36],
        [0.40, 0.22, 0.16],
    ]
)
TREE_PALETTE = np.array(
    [
        [0.06, 0.16, 0.04],
        [0.09, 0.20, 0.05],
        [0.12, 0.22, 0.06],
        [0.05, 0.12, 0.05],
        [0.16, 0.20, 0.06],
        [0.22, 0.14, 0.05],
        # crowns a roof's colour would pass for
        [0.30, 0.08, 0.04],  # autumn red
        [0.28, 0.16, 0.06],  # autumn brown
        [0.19, 0.18, 0.17],  # bare grey crown
    ]
)
assert len(TREE_PALETTE) == TREE_HUES


@dataclass
class World:
    """The scene geometry and what is needed to shade and label it.

    Attributes
    ----------
    vertices : (V, 3) float64, world metres
    triangles : (T, 3) int32
    material : (T,) int32, index into the material table
    cls : (T,) uint8, class code
    building : (T,) int32, building id (0 = none)
    axis : (T, 2) float32, texture axis
    zref : (T,) float32, reference height (building base, for window rows)
    mat_kind : (M,) int32; mat_rgb : (M, 3) linear albedo; mat_param : (M, 4)
    terrain : Terrain
    roads : list of dict
    """

    vertices: np.ndarray
    triangles: np.ndarray
    material: np.ndarray
    cls: np.ndarray
    building: np.ndarray
    axis: np.ndarray
    zref: np.ndarray
    mat_kind: np.ndarray
    mat_rgb: np.ndarray
    mat_param: np.ndarray
    terrain: Terrain
    roads: list

    def raycasting_scene(self, *, mask: np.ndarray | None = None) -> RayScene:
        """An Open3D ray-casting scene of the triangles (all, or those in ``mask``).

        Primitive ids of hits index the selected triangles in order.
        """
        return raycasting_scene(
            self.vertices, self.triangles if mask is None else self.triangles[mask]
        )


class _Builder:
    def __init__(self):
        self.v, self.t, self.mat, self.cls, self.bid, self.axis, self.zref = ([] for _ in range(7))
        self.n = 0
        self.kinds, self.rgbs, self.params = [], [], []

    def material(self, kind, rgb, param=(0, 0, 0, 0)) -> int:
        self.kinds.append(kind)
        self.rgbs.append(np.asarray(rgb, dtype=np.float64))
        self.params.append(np.asarray(param, dtype=np.float64))
        return len(self.kinds) - 1

    def add(self, verts, tris, mat, cls, bid=0, axis=None, zref=0.0):
        tris = np.asarray(tris, dtype=np.int64)
        m = len(tris)
        self.v.append(np.asarray(verts, dtype=np.float64))
        self.t.append(tris + self.n)
        self.n += len(verts)
        self.mat.append(np.broadcast_to(np.asarray(mat, dtype=np.int32), (m,)))
        self.cls.append(np.broadcast_to(np.asarray(cls, dtype=np.uint8), (m,)))
        self.bid.append(np.full(m, bid, np.int32))
        ax = np.tile([1.0, 0.0], (m, 1)) if axis is None else np.asarray(axis)
        self.axis.append(ax.astype(np.float32))
        self.zref.append(np.full(m, zref, np.float32))


def build_world(layout: Layout, terrain: Terrain, margin: float, rng) -> World:
    """Assemble ground, buildings and trees into one :class:`World`.

    Parameters
    ----------
    layout : Layout
    terrain : Terrain
    margin : float
        Width of the coarse ground around the area of interest, so that oblique
        views see ground rather than the void, metres.
    rng : numpy.random.Generator
        Picks roof, facade and tree materials.
    """
    b = _Builder()
    kinds = [K_ASPHALT, K_PAVEMENT, K_GRASS, K_SOIL, K_RURAL]
    base_rgb = {
        "asphalt": [0.085, 0.085, 0.09],
        "pavement": [0.34, 0.33, 0.31],
        "grass": [0.10, 0.22, 0.05],
        "soil": [0.30, 0.21, 0.13],
        "rural": [0.14, 0.20, 0.07],
    }
    for k, name in zip(kinds, GROUND_MATERIALS, strict=True):
        b.material(k, base_rgb[name])
    _add_ground(b, layout, terrain, margin)
    for spec in layout.buildings:
        _add_building(b, spec, terrain, rng)
    tree_mats = [b.material(K_TREE, c) for c in TREE_PALETTE]
    trunk_mat = b.material(K_TRUNK, [0.18, 0.12, 0.07])
    for tree in layout.trees:
        _add_tree(b, tree, terrain, tree_mats, trunk_mat, rng)
    return World(
        vertices=np.concatenate(b.v),
        triangles=np.concatenate(b.t).astype(np.int32),
        material=np.concatenate(b.mat),
        cls=np.concatenate(b.cls),
        building=np.concatenate(b.bid),
        axis=np.concatenate(b.axis),
        zref=np.concatenate(b.zref),
        mat_kind=np.array(b.kinds, np.int32),
        mat_rgb=np.array(b.rgbs),
        mat_param=np.array(b.params),
        terrain=terrain,
        roads=layout.roads,
    )


def _add_ground(b: _Builder, layout: Layout, terrain: Terrain, margin: float) -> None:
    g = layout.ground_grid
    x0, y0, x1, y1 = g.bounds
    coarse = max(10.0, margin / 20)
    xs = graded_axis(x0, x1, g.gsd, margin, coarse)
    ys = graded_axis(y0, y1, g.gsd, margin, coarse)
    X, Y = np.meshgrid(xs, ys)
    Z = terrain.height(X, Y)
    verts = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    ny, nx = len(ys) - 1, len(xs) - 1
    j, i = np.meshgrid(np.arange(nx), np.arange(ny))
    v00 = (i * len(xs) + j).ravel()
    v10, v01, v11 = v00 + 1, v00 + len(xs), v00 + len(xs) + 1
    tris = np.empty((2 * v00.size, 3), np.int64)
    tris[0::2] = np.column_stack([v00, v10, v11])
    tris[1::2] = np.column_stack([v00, v11, v01])
    # material per cell: the layout raster inside the area of interest, rural outside
    cx = 0.5 * (xs[:-1] + xs[1:])
    cy = 0.5 * (ys[:-1] + ys[1:])
    CX, CY = np.meshgrid(cx, cy)
    row, col = g.world_to_cell(CX, CY)
    row, col = np.round(row).astype(int), np.round(col).astype(int)
    inside = (row >= 0) & (row < g.height) & (col >= 0) & (col < g.width)
    inside &= (CX > x0) & (CX < x1) & (CY > y0) & (CY < y1)
    mat = np.full(CX.shape, RURAL, np.int32)
    mat[inside] = layout.ground_material[row[inside], col[inside]]
    mat = np.repeat(mat.ravel(), 2)
    b.add(verts, tris, mat, GROUND_CLASS[mat])


def building_faces(spec, base_z: float):
    """Roof faces of all wings of a building, at absolute heights."""
    faces = []
    tiers = [(w, base_z + h) for w, h in spec.tiers]
    for k, wing in enumerate(spec.wings):
        faces += wing_roof_faces(
            wing,
            spec.roof_type,
            base_z + spec.eave,
            pitch_deg=spec.pitch,
            tiers=tiers if k == 0 else (),
        )
    return faces


def _add_building(b: _Builder, spec, terrain: Terrain, rng) -> None:
    xy = np.asarray(spec.footprint.exterior.coords)
    base_z = float(terrain.height(xy[:, 0], xy[:, 1]).min())
    spec.base_z = base_z
    mesh = building_mesh(building_faces(spec, base_z), base_z - 1.5)
    roof = ROOF_PALETTE[rng.integers(len(ROOF_PALETTE))] * rng.uniform(0.85, 1.15, 3)
    flat = spec.roof_type in ("flat", "multi-level")
    roof_mat = b.material(K_ROOF, roof, (1.0 if flat else 0.0, rng.uniform(0.28, 0.4), 0, 0))
    facade = FACADE_PALETTE[rng.integers(len(FACADE_PALETTE))] * rng.uniform(0.9, 1.1, 3)
    floor_h = 3.0 if spec.eave < 30 else 3.6
    facade_mat = b.material(
        K_FACADE, facade, (rng.uniform(2.4, 3.4), rng.uniform(0.9, 1.5), floor_h, base_z)
    )
    mat = np.where(mesh.part == 0, roof_mat, facade_mat)
    b.add(mesh.vertices, mesh.triangles, mat, CLASS_BUILDING, spec.id, mesh.axis, base_z)


@functools.lru_cache(maxsize=1)
def _unit_sphere() -> tuple[np.ndarray, np.ndarray]:
    s = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=8)
    return np.asarray(s.vertices).copy(), np.asarray(s.triangles).copy()


def _add_tree(b: _Builder, tree, terrain: Terrain, tree_mats, trunk_mat, rng) -> None:
    gz = float(terrain.height(tree.x, tree.y))
    v, t = _unit_sphere()
    lumpy = 1.0 + 0.18 * (rng.random(len(v)) - 0.5)
    cz = gz + tree.trunk_height + tree.crown_height
    crown = v * lumpy[:, None] * [tree.crown_radius, tree.crown_radius, tree.crown_height]
    crown = crown + [tree.x, tree.y, cz]
    b.add(crown, t, tree_mats[tree.hue], CLASS_TREE)
    # trunk: a thin square prism from below ground into the crown
    r = 0.15 + 0.03 * tree.crown_radius
    top = cz - 0.5 * tree.crown_height
    sq = np.array([[-r, -r], [r, -r], [r, r], [-r, r]])
    verts = np.vstack(
        [
            np.column_stack([sq + [tree.x, tree.y], np.full(4, gz - 0.5)]),
            np.column_stack([sq + [tree.x, tree.y], np.full(4, top)]),
        ]
    )
    tris = []
    for i in range(4):
        j = (i + 1) % 4
        tris += [[i, j, 4 + j], [i, 4 + j, 4 + i]]
    b.add(verts, tris, trunk_mat, CLASS_TREE)

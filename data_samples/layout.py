"""City layout: roads, blocks, parcels, building footprints, trees, ground materials.

Everything here is 2D planning; heights come from :mod:`data_samples.roofs`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from rasterio.features import rasterize
from shapely.geometry import Point, Polygon, box

from workbench.raster import Grid

from .roofs import Wing

# ground materials (cells of the ground mesh)
ASPHALT, PAVEMENT, GRASS, SOIL, RURAL = 0, 1, 2, 3, 4
GROUND_MATERIALS = ("asphalt", "pavement", "grass", "soil", "rural")
GROUND_CLASS = np.array([1, 1, 2, 1, 2], dtype=np.uint8)  # workbench class codes


@dataclass
class BuildingSpec:
    """One building of the synthetic city (heights relative to ``base_z``)."""

    id: int
    shape: str  # rect, L, T, U, courtyard
    wings: list[Wing]
    roof_type: str
    eave: float  # eave height above base, metres
    pitch: float  # degrees
    tiers: list[tuple[Wing, float]] = field(default_factory=list)  # (wing, height above base)
    footprint: Polygon | None = None
    base_z: float = 0.0
    rotated: bool = False


TREE_HUES = 9  # colours of crowns: data_samples.world.TREE_PALETTE


@dataclass
class TreeSpec:
    x: float
    y: float
    crown_radius: float
    crown_height: float  # vertical semi-axis of the crown
    trunk_height: float  # ground to the bottom of the crown
    hue: int  # index into the tree palette


@dataclass
class Layout:
    buildings: list[BuildingSpec]
    trees: list[TreeSpec]
    ground_grid: Grid
    ground_material: np.ndarray  # (H, W) uint8 on ground_grid
    roads: list[dict]


def _road_centres(half: float, block: tuple[float, float], rng) -> list[float]:
    out = []
    p = -half + rng.uniform(0.3, 0.6) * block[0]
    while p < half - 8.0:
        out.append(float(p))
        p += rng.uniform(*block)
    return out


def _wings_for_shape(shape: str, W: float, H: float, rng) -> list[Wing]:
    """Wings of a footprint of overall size W x H centred at the origin (angle 0)."""

    def wing(x0, y0, x1, y1):
        cx, cy, w, h = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2
        return Wing(cx, cy, w, h, 0.0) if w >= h else Wing(cx, cy, h, w, np.pi / 2)

    x0, y0, x1, y1 = -W / 2, -H / 2, W / 2, H / 2
    d = float(np.clip(rng.uniform(0.3, 0.45) * min(W, H), 5.0, 12.0))
    if shape == "rect":
        return [wing(x0, y0, x1, y1)]
    if shape == "L":
        return [wing(x0, y0, x1, y0 + d), wing(x0, y0, x0 + d, y1)]
    if shape == "T":
        c = rng.uniform(-0.15, 0.15) * W
        return [wing(x0, y1 - d, x1, y1), wing(c - d / 2, y0, c + d / 2, y1)]
    if shape == "U":
        return [wing(x0, y0, x1, y0 + d), wing(x0, y0, x0 + d, y1), wing(x1 - d, y0, x1, y1)]
    if shape == "courtyard":
        return [
            wing(x0, y0, x1, y0 + d),
            wing(x0, y1 - d, x1, y1),
            wing(x0, y0, x0 + d, y1),
            wing(x1 - d, y0, x1, y1),
        ]
    raise ValueError(shape)


def _place(wings: list[Wing], cx: float, cy: float, angle: float) -> list[Wing]:
    c, s = np.cos(angle), np.sin(angle)
    return [
        Wing(cx + c * w.cx - s * w.cy, cy + s * w.cx + c * w.cy, w.a, w.b, w.angle + angle)
        for w in wings
    ]


def _footprint(wings: list[Wing]) -> Polygon:
    return shapely.union_all([Polygon(w.corners()) for w in wings])


def _choose_roof(shape: str, tall: bool, W: float, H: float, rng) -> str:
    if tall:
        return str(rng.choice(["flat", "multi-level"], p=[0.45, 0.55]))
    if shape != "rect":
        return str(rng.choice(["gable", "hipped", "flat"], p=[0.45, 0.35, 0.2]))
    square = max(W, H) / min(W, H) < 1.3
    opts = ["gable", "hipped", "flat", "shed", "mansard", "multi-level"]
    p = [0.3, 0.22, 0.14, 0.1, 0.12, 0.12]
    if square:
        opts.append("pyramid")
        p = [x * 0.8 for x in p] + [0.2]
    return str(rng.choice(opts, p=p))


def _make_building(bid, parcel: Polygon, rng, preset, force_tall: bool) -> BuildingSpec | None:
    x0, y0, x1, y1 = parcel.bounds
    setback = rng.uniform(1.5, 3.0)
    W, H = x1 - x0 - 2 * setback, y1 - y0 - 2 * setback
    if min(W, H) < 6.0:
        return None
    tall = force_tall and min(W, H) >= 14.0
    m = min(W, H)
    if tall:
        shape = str(rng.choice(["rect", "L", "T"], p=[0.6, 0.2, 0.2]) if m >= 20 else "rect")
    elif m >= 24.0:
        shape = str(rng.choice(["rect", "L", "T", "U", "courtyard"], p=[0.2, 0.2, 0.2, 0.2, 0.2]))
    elif m >= 16.0:
        shape = str(rng.choice(["rect", "L", "T", "U"], p=[0.35, 0.3, 0.2, 0.15]))
    else:
        shape = str(rng.choice(["rect", "L"], p=[0.7, 0.3]))
    # residential houses are not as large as the whole parcel
    if not tall and shape == "rect":
        W = min(W, rng.uniform(8.0, 18.0))
        H = min(H, rng.uniform(8.0, 14.0))
    rotated = rng.random() < 0.25
    angle = float(np.radians(rng.uniform(8, 35)) * rng.choice([-1, 1])) if rotated else 0.0
    base_angle = float(rng.choice([0.0, np.pi / 2])) if shape == "rect" else 0.0
    wings = _wings_for_shape(shape, W, H, rng)
    inner = parcel.buffer(-setback + 0.5, join_style="mitre")
    cx, cy = parcel.centroid.x, parcel.centroid.y
    for _ in range(8):  # shrink until the rotated footprint fits the parcel
        placed = _place(wings, cx, cy, angle + base_angle)
        fp = _footprint(placed)
        if inner.contains(fp):
            break
        wings = [Wing(w.cx * 0.9, w.cy * 0.9, w.a * 0.9, w.b * 0.9, w.angle) for w in wings]
    else:
        return None
    if min(min(w.a, w.b) for w in placed) < 2.5:
        return None
    roof = _choose_roof(shape, tall, W, H, rng)
    pitch = float(rng.uniform(25.0, 45.0))
    tiers: list[tuple[Wing, float]] = []
    if tall:
        hi = preset.max_height * (0.7 if roof == "multi-level" else 1.0)
        eave = float(rng.uniform(min(18.0, 0.5 * hi), hi))
    elif roof == "flat" and rng.random() < 0.25:
        eave = float(rng.uniform(3.0, 4.0))  # garages, sheds: the low end of the range
    else:
        eave = float(3.0 * rng.integers(1, 5) + rng.uniform(0.0, 0.8))
    if roof in ("gable", "hipped", "pyramid", "mansard", "shed"):
        top = eave + max(w.b for w in placed) * np.tan(np.radians(pitch)) * (
            2 if roof == "shed" else 1
        )
        if top > preset.max_height:
            eave = max(3.0, eave - (top - preset.max_height))
            pitch = min(pitch, 30.0)
    if roof == "multi-level":
        base = placed[0]
        h = eave
        cur = Wing(base.cx, base.cy, base.a, base.b, base.angle)
        for _ in range(int(rng.integers(1, 4))):  # 2 to 4 levels in all
            fa, fb = rng.uniform(0.45, 0.8), rng.uniform(0.45, 0.8)
            na, nb = cur.a * fa, cur.b * fb
            if min(na, nb) < 2.5:
                break
            off = rng.uniform(-1, 1) * (cur.a - na) * 0.8
            c, s = np.cos(cur.angle), np.sin(cur.angle)
            cur = Wing(cur.cx + c * off, cur.cy + s * off, na, nb, cur.angle)
            h = min(h + float(rng.uniform(3.0, 12.0)), preset.max_height)
            tiers.append((cur, h))
        if not tiers:
            roof = "flat"
    return BuildingSpec(bid, shape, placed, roof, eave, pitch, tiers, fp, rotated=rotated)


def make_layout(preset, rng: np.random.Generator) -> Layout:
    """Plan a city of the preset's size, centred at the origin."""
    half = preset.size / 2
    grid = Grid.from_bounds(-half, -half, half, half, preset.ground_cell)
    roads = []
    for axis in ("x", "y"):
        for c in _road_centres(half, preset.block, rng):
            roads.append(
                {
                    "axis": axis,
                    "center": c,
                    "width": float(rng.uniform(6.0, 10.0)),
                    "pavement": float(rng.uniform(2.0, 3.0)),
                }
            )

    def band(r, extra):
        w = r["width"] / 2 + extra
        if r["axis"] == "x":  # a road of constant x, running north-south
            return box(r["center"] - w, -half - 50, r["center"] + w, half + 50)
        return box(-half - 50, r["center"] - w, half + 50, r["center"] + w)

    road_area = shapely.union_all([band(r, 0) for r in roads]) if roads else Polygon()
    street_area = shapely.union_all([band(r, r["pavement"]) for r in roads]) if roads else Polygon()
    aoi = box(-half + 1.0, -half + 1.0, half - 1.0, half - 1.0)
    blocks_geom = aoi.difference(street_area)
    blocks = [b for b in shapely.get_parts(blocks_geom) if b.area > 100.0]
    blocks.sort(key=lambda b: (round(b.centroid.y, 3), round(b.centroid.x, 3)))

    buildings: list[BuildingSpec] = []
    trees: list[TreeSpec] = []
    shapes_mat: list[tuple[Polygon, int]] = []
    next_id = 1
    for blk in blocks:
        bx0, by0, bx1, by1 = blk.bounds
        kind = rng.choice(
            ["residential", "park", "lot"],
            p=[1 - preset.parks - preset.lots, preset.parks, preset.lots],
        )
        if min(bx1 - bx0, by1 - by0) < 12.0:
            kind = "park"
        if kind == "park":
            _scatter_trees(blk, rng, preset.trees_per_hectare * 2.5, trees, [])
            if rng.random() < 0.3:
                shapes_mat.append((blk.buffer(-rng.uniform(3, 6)), SOIL))
            continue
        if kind == "lot":
            shapes_mat.append((blk, ASPHALT if rng.random() < 0.6 else SOIL))
            continue
        tall_block = rng.random() < preset.tall_fraction * 2.0
        for parcel in _parcels(blk, rng, preset.parcel):
            yard = SOIL if rng.random() < 0.15 else GRASS
            shapes_mat.append((parcel.buffer(-0.3), yard))
            if rng.random() > 0.88:
                _scatter_trees(parcel, rng, preset.trees_per_hectare * 2, trees, [])
                continue
            spec = _make_building(next_id, parcel, rng, preset, tall_block)
            if spec is None:
                continue
            buildings.append(spec)
            next_id += 1
            shapes_mat.append((spec.footprint.buffer(1.0, join_style="mitre"), PAVEMENT))
            _trees_near_building(spec.footprint, parcel, rng, trees)
    # street trees along pavements
    for r in roads:
        if rng.random() < 0.5:
            continue
        side = rng.choice([-1, 1])
        off = side * (r["width"] / 2 + r["pavement"] * 0.5)
        for s in np.arange(-half + 6, half - 6, rng.uniform(9.0, 13.0)):
            x, y = (r["center"] + off, s) if r["axis"] == "x" else (s, r["center"] + off)
            p = Point(x, y)
            if road_area.distance(p) < 1.0 or any(b.footprint.distance(p) < 3 for b in buildings):
                continue
            trees.append(_tree(x, y, rng, small=True))
    mat = _rasterize_materials(grid, road_area, street_area, shapes_mat)
    return Layout(buildings, trees, grid, mat, roads)


def _parcels(blk: Polygon, rng, widths: tuple[float, float]) -> list[Polygon]:
    x0, y0, x1, y1 = blk.bounds
    w, h = x1 - x0, y1 - y0
    along_x = w >= h
    length, depth = (w, h) if along_x else (h, w)
    rows = 2 if depth > 44.0 else 1
    out = []
    for r in range(rows):
        d0 = r * depth / rows
        d1 = (r + 1) * depth / rows
        pos = 0.0
        while pos < length - 8.0:
            step = rng.uniform(*widths)
            if length - (pos + step) < 10.0:
                step = length - pos
            a0, a1 = pos, pos + step
            rect = (
                box(x0 + a0, y0 + d0, x0 + a1, y0 + d1)
                if along_x
                else box(x0 + d0, y0 + a0, x0 + d1, y0 + a1)
            )
            rect = rect.intersection(blk)
            if rect.area > 60.0 and isinstance(rect, Polygon):
                out.append(rect)
            pos += step
    return out


def _tree(x, y, rng, small=False) -> TreeSpec:
    r = rng.uniform(1.8, 3.2) if small else rng.uniform(2.0, 5.0)
    return TreeSpec(
        float(x),
        float(y),
        float(r),
        float(r * rng.uniform(0.75, 1.25)),
        float(rng.uniform(1.5, 4.5)),
        int(rng.integers(0, TREE_HUES)),
    )


def _scatter_trees(area: Polygon, rng, per_ha: float, trees, avoid) -> None:
    n = rng.poisson(per_ha * area.area / 1e4)
    x0, y0, x1, y1 = area.bounds
    for _ in range(n):
        x, y = rng.uniform(x0, x1), rng.uniform(y0, y1)
        p = Point(x, y)
        if area.buffer(-1.5).contains(p) and all(a.distance(p) > 2.0 for a in avoid):
            trees.append(_tree(x, y, rng))


def _trees_near_building(fp: Polygon, parcel: Polygon, rng, trees) -> None:
    """Yard trees, some close enough for their crowns to overhang the roof."""
    for _ in range(int(rng.integers(0, 3))):
        ring = fp.exterior
        p = ring.interpolate(rng.uniform(0, ring.length))
        c = fp.centroid
        d = np.array([p.x - c.x, p.y - c.y])
        d /= np.linalg.norm(d) + 1e-9
        dist = rng.uniform(1.0, 4.0)
        x, y = p.x + d[0] * dist, p.y + d[1] * dist
        q = Point(x, y)
        if parcel.buffer(-1.0).contains(q) and fp.distance(q) > 0.8:
            trees.append(_tree(x, y, rng))


def _rasterize_materials(grid: Grid, road_area, street_area, shapes_mat) -> np.ndarray:
    shapes = [(street_area, PAVEMENT), (road_area, ASPHALT)]
    # parcels and lots first, roads last so they stay on top
    items = [(g, v) for g, v in shapes_mat if not g.is_empty] + [
        (g, v) for g, v in shapes if not g.is_empty
    ]
    if not items:
        return np.full(grid.shape, GRASS, np.uint8)
    return rasterize(
        items, out_shape=grid.shape, transform=grid.transform, fill=GRASS, dtype="uint8"
    )

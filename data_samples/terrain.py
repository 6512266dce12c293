"""Terrain of the synthetic city: a gently sloped, gently undulating height field."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .noise import fbm


@dataclass(frozen=True)
class Terrain:
    """z(x, y) = z0 + gx x + gy y + relief * fbm(x, y); metres."""

    z0: float
    gx: float
    gy: float
    relief: float
    scale: float
    seed: int

    @classmethod
    def random(cls, rng: np.random.Generator, slope: float, relief: float) -> Terrain:
        g = slope * rng.uniform(0.4, 1.0)
        a = rng.uniform(0, 2 * np.pi)
        return cls(
            z0=float(rng.uniform(5.0, 40.0)),
            gx=float(g * np.cos(a)),
            gy=float(g * np.sin(a)),
            relief=float(relief if slope > 0 else 0.0),
            scale=150.0,
            seed=int(rng.integers(1 << 30)),
        )

    def height(self, x, y) -> np.ndarray:
        """Terrain height at world (x, y), metres."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        z = self.z0 + self.gx * x + self.gy * y
        if self.relief:
            z = z + self.relief * fbm(x, y, self.scale, self.seed, octaves=3)
        return z

    def to_dict(self) -> dict:
        return asdict(self)


def graded_axis(lo: float, hi: float, cell: float, margin: float, coarse: float) -> np.ndarray:
    """Vertex coordinates: ``cell`` spacing on [lo, hi], growing to ``coarse`` outside.

    The result is one tensor-product axis, so the ground mesh has no T-junctions.
    """
    inner = lo + cell * np.arange(int(round((hi - lo) / cell)) + 1)
    steps, d, pos = [], cell, 0.0
    while pos < margin:
        d = min(d * 1.5, coarse)
        pos += d
        steps.append(pos)
    steps = np.array(steps)
    return np.concatenate([lo - steps[::-1], inner, hi + steps])

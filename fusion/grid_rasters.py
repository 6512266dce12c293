"""The fused whole-grid rasters a view's task reads, kept in files it maps.

A view's features read the DTM and the geometric cues at the cells its points fall in,
the fused DSM at its stroke points', and the DSM surface where its unmatched pixels'
rays meet it. Handed to every worker whole, these would grow each worker's memory with
the area (on the `city` preset the surface alone is 12.5 M triangles); mapped from
``.npy`` files, a task reads only the cells and the window it needs, and a worker's
memory follows a view.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from workbench.engine import disk_full
from workbench.raster import Grid

from .dsm_depth import DsmSurface


@dataclass
class GridRasters:
    """Whole-grid rasters as ``.npy`` files, and the DSM surface made of one of them.

    Attributes
    ----------
    grid : Grid
    folder : Path
        Where the files are.
    names : tuple of str
        The rasters, ``<folder>/<name>.npy`` each: ``dsm``, ``dtm`` (H, W), ``filled``
        (H, W, the surface's heights) and, with the geometric cues, ``cues`` (G, H, W).
    surface_origin : (3,) float
        The surface's local origin (:class:`~fusion.dsm_depth.DsmSurface`), metres.
    surface_z_range : (lowest, highest) of its heights, metres.
    """

    grid: Grid
    folder: Path
    names: tuple
    surface_origin: np.ndarray
    surface_z_range: tuple
    _surface: DsmSurface | None = field(default=None, repr=False, compare=False)

    def __getstate__(self):  # each process makes its own surface, and keeps its tiles
        return {**self.__dict__, "_surface": None}

    @classmethod
    def write(cls, folder: Path, grid: Grid, surface: DsmSurface, **rasters) -> GridRasters:
        """Write ``rasters`` (name -> array, None to leave it out) and the surface's
        heights to ``folder``."""
        kept = {name: a for name, a in {**rasters, "filled": surface.filled}.items()
                if a is not None}  # fmt: skip
        for name, array in kept.items():
            _save(Path(folder) / f"{name}.npy", array)
        return cls(grid, Path(folder), tuple(kept), surface.origin, surface.z_range)

    def keep(self, name: str, array: np.ndarray) -> Path:
        """Write another array (on a grid of its own) beside the rasters; its file."""
        path = self.folder / f"{name}.npy"
        _save(path, array)
        return path

    def read(self, name: str) -> np.ndarray | None:
        """The raster ``name``, memory-mapped read-only (None if it was left out):
        indexing it reads only the cells asked for."""
        if name not in self.names:
            return None
        return np.load(self.folder / f"{name}.npy", mmap_mode="r")

    def surface(self) -> DsmSurface:
        """The DSM surface of the heights' file, made once in this process: its
        ``depth_at`` reads and keeps the tiles it casts against, within a budget."""
        if self._surface is None:
            self._surface = DsmSurface.of_filled(
                self.folder / "filled.npy", self.grid, self.surface_origin, self.surface_z_range
            )
        return self._surface


def _save(path: Path, array: np.ndarray) -> None:
    """``np.save``, a full disk named in one line (the tasks finished before are kept)."""
    try:
        np.save(path, array)
    except OSError as e:
        full = disk_full(e, path)
        if full is None:
            raise
        raise full from None

"""Writing a fusion run: GeoTIFFs, fusion.json and preview.png."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from workbench.imageio import write_rgb
from workbench.pictures import colorize_classes, colorize_height, contact_sheet
from workbench.raster import WindowedRaster, read_decimated, read_raster, write_raster

from .classifier import CLASS_NAMES

PREVIEW_CELLS = 1024  # a preview's longer side, read from the rasters' overviews


# the run's rasters: file, product, dtype, bands, nodata, band descriptions
RASTERS = (
    ("ortho.tif", "ortho", np.uint8, 3, None, None),
    ("dsm.tif", "dsm", np.float32, 1, None, None),
    ("dtm.tif", "dtm", np.float32, 1, None, None),
    ("ndsm.tif", "ndsm", np.float32, 1, None, None),
    ("class_prob.tif", "class_prob", np.float32, 4, None, list(CLASS_NAMES)),
    ("class.tif", "classes", np.uint8, 1, 0, None),
    (
        "count.tif",
        "count",
        np.int16,
        1,
        None,
        ["observations per cell (-1: interpolated small hole)"],
    ),
)


# over the cells no view saw, from views with depth maps only (fusion.hidden_ceiling)
CEILING = ("ceiling.tif", "ceiling", np.float32, 1, None,
           ["lowest height a view sees through an unseen cell's column (NaN: seen)"])  # fmt: skip


def _bands(product: str, data: np.ndarray) -> np.ndarray:
    """A product's array as bands: the ortho (h, w, 3) becomes (3, h, w)."""
    return np.moveaxis(data, -1, 0) if product == "ortho" else data


def write_fusion(out: Path, result, crs, record: dict) -> None:
    """Write every product of a :class:`~fusion.scene_fusion.FusionResult` into ``out``."""
    g = result.grid
    for name, product, dtype, _, nodata, descriptions in RASTERS + (CEILING,) * (
            result.ceiling is not None):  # fmt: skip
        data = _bands(product, getattr(result, product))
        write_raster(out / name, data.astype(dtype, copy=False), g, crs, nodata=nodata,
                     descriptions=descriptions)  # fmt: skip
    if result.normal is not None:
        write_raster(out / "normal.tif", result.normal, g, crs, descriptions=["nx", "ny", "nz"])
    write_record(out, record)
    write_preview(out, result.ortho, result.ndsm, result.classes)


def write_record(out: Path, record: dict) -> None:
    (out / "fusion.json").write_text(json.dumps(record, indent=1, default=_jsonable) + "\n")


def write_preview(out: Path, ortho: np.ndarray, ndsm: np.ndarray, classes: np.ndarray) -> None:
    """preview.png: the ortho (h, w, 3), the nDSM and the classes (h, w) side by side."""
    write_rgb(
        out / "preview.png",
        contact_sheet(
            [[(ortho, "fused ortho"), (colorize_height(ndsm), "nDSM"),
              (colorize_classes(classes), "classes")]],
            height=360,
        ),
    )  # fmt: skip


class FusionWindows:
    """The run's rasters written block by block (:mod:`fusion.blocks`) into ``out``.

    Parameters
    ----------
    out : path
        The run's (temporary) folder.
    grid : Grid
        The whole grid.
    crs : CRS or None
    ceiling : bool
        Whether the blocks' products hold a ``ceiling`` (views with depth maps do).
    """

    def __init__(self, out: Path, grid, crs, *, ceiling: bool = False):
        self.out = Path(out)
        self.files = {}
        try:
            for name, product, dtype, bands, nodata, described in RASTERS + (CEILING,) * ceiling:
                self.files[product] = WindowedRaster(
                    out / name, grid, crs, dtype, bands, nodata=nodata, descriptions=described
                )
        except BaseException:
            self.discard()
            raise

    def __call__(self, block, products: dict) -> None:
        """Write a block's products (:func:`~fusion.blocks.fuse_in_blocks`) inside it."""
        for product, f in self.files.items():
            f.write(_bands(product, products[product]), *block.inner)

    def close(self, record: dict) -> None:
        """The rasters as COGs, ``fusion.json`` and the preview (from the overviews)."""
        for f in self.files.values():
            f.close()
        write_record(self.out, record)
        ortho = np.moveaxis(read_decimated(self.out / "ortho.tif", PREVIEW_CELLS), 0, -1)
        ndsm = read_decimated(self.out / "ndsm.tif", PREVIEW_CELLS)[0]
        classes = read_decimated(self.out / "class.tif", PREVIEW_CELLS)[0]
        write_preview(self.out, ortho, ndsm, classes)

    def discard(self) -> None:
        for f in self.files.values():
            f.discard()


def read_fusion(folder: Path):
    """A run folder's rasters, whole, as a :class:`~fusion.scene_fusion.FusionResult`
    (no ablation, forest or record)."""
    from .scene_fusion import FusionResult

    data = {}
    for name, product, dtype, _, _, _ in RASTERS:
        bands, grid, _ = read_raster(Path(folder) / name)
        data[product] = _bands_back(product, bands).astype(dtype, copy=False)
    classes = data.pop("classes")
    return FusionResult(grid, **data, class_map=classes)


def _bands_back(product: str, bands: np.ndarray) -> np.ndarray:
    """:func:`_bands` undone: (3, h, w) -> (h, w, 3) for the ortho, single bands -> (h, w)."""
    if product == "ortho":
        return np.moveaxis(bands, 0, -1)
    return bands if product == "class_prob" else bands[0]


def _jsonable(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o))

"""Modeling paths: each a folder, each a function from its inputs and options to a
:class:`~workbench.model_run.ModelRun`, registered here for ``workbench model NAME``.

- :mod:`modeling.superpixel`: super-pixels, class CRF, roof prototypes, LOD2 meshes;
- :mod:`modeling.voxel`: photo-consistency proxies from footprints, graph-cut textures;
- :mod:`modeling.parametric`: a level set, footprint priors in competition, five-parameter
  roofs (the variational paper);
- :mod:`modeling.blocks`: 2D supports, a library of parametric 3D blocks, RJMCMC under
  simulated annealing (the DEM-blocks paper);
- :mod:`modeling.lod`: MRF labelling, regular roof planes, segment arrangements, LOD0/1/2
  (the LOD paper);
- :mod:`modeling.shared`: what more than one path uses (graph cuts, planes, roof meshes,
  outline regularity, roof types). No path imports another path.

To add a path: a folder with an options dataclass, a run function returning a
``ModelRun``, and a ``SPEC`` in its ``__init__``; then list it in ``PATHS`` below.
"""

from . import blocks, lod, parametric, superpixel, voxel
from .registry import Input, PathSpec

PATHS: dict[str, PathSpec] = {
    spec.name: spec
    for spec in (superpixel.SPEC, voxel.SPEC, parametric.SPEC, blocks.SPEC, lod.SPEC)
}

__all__ = ["PATHS", "Input", "PathSpec"]

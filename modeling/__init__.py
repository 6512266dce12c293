"""Modeling paths (super-pixel LOD2 meshes, voxel proxies with graph-cut textures).

Not implemented yet: tracked by the modeling issues. The package exists so that
the layout of the workbench is in place.
"""

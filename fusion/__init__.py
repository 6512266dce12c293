"""Fusion of calibrated views or LiDAR into ortho colour, height and class rasters.

Not implemented yet: tracked by the fusion issue. The package exists so that the
layout of the workbench is in place.
"""

"""Geometry more than one modeling path uses (graph cuts, which the fusion uses too, are
in :mod:`workbench.graph_cuts`): roof planes (:mod:`.planes`), roof meshes from faces and planes
(:mod:`.roof_mesh`), outline regularity (:mod:`.outline_regularity`) and roof types
(:mod:`.roof_types`)."""

"""City workbench: scene I/O, the command line, metrics and reports.

The fusion step lives in :mod:`fusion`, the modeling paths in :mod:`modeling`,
and the synthetic benchmark city in :mod:`data_samples`.
"""

__version__ = "0.1.0"

"""The synthetic benchmark city: a scene rendered from calibrated cameras, with full truth.

>>> from data_samples import generate_sample
>>> meta = generate_sample("city_tiny", "tiny", seed=0)  # doctest: +SKIP
"""

from .generate import generate_sample
from .presets import PRESETS, Preset

__all__ = ["PRESETS", "Preset", "generate_sample"]

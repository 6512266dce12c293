"""Stable numbers of the preset names, part of every sample's seed."""

_NAMES = {"tiny": 1, "small": 2, "city": 3}


def preset_index(name: str) -> int:
    """A stable integer per preset name (custom names hash deterministically)."""
    if name in _NAMES:
        return _NAMES[name]
    return sum((i + 1) * ord(c) for i, c in enumerate(name)) + 100

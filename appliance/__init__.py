"""Viper field appliance: position from the skyline a camera sees, matched against a DEM.

The public names, imported on first use (``import appliance`` stays light for the CLI)::

    from appliance import Skyline, load_database, locate
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_PUBLIC = {
    "Skyline": "appliance.skyline",
    "read_skyline_csv": "appliance.skyline",
    "write_skyline_csv": "appliance.skyline",
    "Dem": "appliance.terrain.dem",
    "load_dem": "appliance.terrain.dem",
    "render_skyline": "appliance.terrain.horizon",
    "SkylineDatabase": "appliance.terrain.database",
    "build_database": "appliance.terrain.database",
    "load_database": "appliance.terrain.database",
    "Position": "appliance.locating.position",
    "Move": "appliance.locating.position",
    "locate": "appliance.locating.position",
    "locate_sequence": "appliance.locating.position",
    "Config": "appliance.config",
    "load_config": "appliance.config",
    "ViperError": "appliance.errors",
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'appliance' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)

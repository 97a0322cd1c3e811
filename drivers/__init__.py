"""Sensor drivers, installed as ``respecd.drivers``.

``DRIVERS`` maps the YAML ``driver:`` key to (module, driver class, config class). Modules
import their hardware SDKs lazily (inside ``start``), so a profile that does not use a
RealSense loads on a machine without pyrealsense2.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from respecd.drivers.base import Driver, DriverConfigBase

# key -> (module under respecd.drivers, driver class name, config class name)
DRIVERS: dict[str, tuple[str, str, str]] = {
    "sim": ("sim", "SimDriver", "SimConfig"),
    "uvc": ("uvc", "UVCDriver", "UVCConfig"),
    "flirone": ("flirone", "FlirOneDriver", "FlirOneConfig"),
    "realsense": ("realsense", "RealSenseDriver", "RealSenseConfig"),
    "replay": ("replay", "ReplayDriver", "ReplayConfig"),
    "iwr6843": ("iwr6843", "IWR6843Driver", "IWR6843Config"),
}


def _load(key: str, index: int) -> type:
    module_name, *names = DRIVERS[key]
    module = importlib.import_module(f"respecd.drivers.{module_name}")
    return getattr(module, names[index])


def driver_class(key: str) -> type[Driver]:
    """The driver class registered under ``key``."""
    return _load(key, 0)


def config_class(key: str) -> type[DriverConfigBase]:
    """The profile entry model of the driver registered under ``key``."""
    return _load(key, 1)


def config_classes() -> list[type[DriverConfigBase]]:
    """Every registered driver's config model, for the profile's discriminated union."""
    return [_load(key, 1) for key in DRIVERS]

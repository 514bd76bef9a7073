"""The optional parts of the appliance, and the error that names the extra to install for one.

The base install (``pip install viper-appliance``) runs the map side and the estimator: ``viper dem``,
``render``, ``precompute``, ``estimate``, ``log``, ``gps``.  The rest needs an extra:

=========  ================  ======================================================================
extra      brings            for
=========  ================  ======================================================================
vision     OpenCV            stitch, skyline, capture, daemon, devices, replay, demo (not
                             ``--skyline-only``), ``calibrate camera``, serve
live       foxglove-sdk      ``capture --live``, ``daemon session --live``
cluster    dask.distributed  ``precompute --tiles``, ``estimate --workers/--scheduler``
rover      pymavlink, pyulog MAVLink odometry and position output, PX4 ULog records, ROS 2-encoded logs
           mcap-ros2-support
all        all four
=========  ================  ======================================================================

:func:`require` imports an optional module where it is used, or raises :class:`MissingExtraError`;
:func:`missing_extra` gives the same error for the ``ModuleNotFoundError`` of a module imported at the
top of a file (OpenCV throughout :mod:`appliance.vision`), so that the CLI says it in one line.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType

from appliance.errors import ViperError

DISTRIBUTION = "viper-appliance"


@dataclass(frozen=True)
class Extra:
    """An extra of the distribution (``name``) and the library it brings, as a user knows it."""

    name: str
    library: str


#: Top-level module -> the extra that installs it.
OPTIONAL_MODULES: dict[str, Extra] = {
    "cv2": Extra("vision", "OpenCV"),
    "foxglove": Extra("live", "foxglove-sdk"),
    "distributed": Extra("cluster", "dask.distributed"),
    "dask": Extra("cluster", "dask.distributed"),
    "pymavlink": Extra("rover", "pymavlink"),
    "pyulog": Extra("rover", "pyulog"),
    "mcap_ros2": Extra("rover", "mcap-ros2-support"),
}


class MissingExtraError(ViperError, ImportError):
    """An optional library is not installed; the message names the extra that brings it."""

    def __init__(self, module: str, purpose: str) -> None:
        extra = OPTIONAL_MODULES[module.partition(".")[0]]
        super().__init__(f"{purpose} needs {extra.library}, which is not installed: "
                         f"pip install '{DISTRIBUTION}[{extra.name}]'")
        self.extra = extra.name


def require(module: str, purpose: str) -> ModuleType:
    """``module`` (one of :data:`OPTIONAL_MODULES` or a submodule of one) imported, or a
    :class:`MissingExtraError` saying that ``purpose`` (e.g. "the live view (--live)") needs its extra."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        error = missing_extra(exc, purpose)
        if error is None:
            raise
        raise error from None


def missing_extra(exc: ModuleNotFoundError, purpose: str = "this command") -> MissingExtraError | None:
    """The :class:`MissingExtraError` for ``exc`` if the module not found is an optional one, else None
    (a module of the base install missing is a broken install, not a missing extra)."""
    top = (exc.name or "").partition(".")[0]
    return MissingExtraError(top, purpose) if top in OPTIONAL_MODULES else None

"""One error hierarchy for the whole appliance.

Every error the appliance raises on purpose derives from :class:`ViperError`; subclasses also
inherit the matching builtin so callers may catch either.  The CLI turns any ``ViperError`` into a
single line on stderr and a non-zero exit status.
"""

from __future__ import annotations

import enum
from typing import TypeVar


class ViperError(Exception):
    """Root of the appliance's errors."""

    exit_code = 1


class ConfigError(ViperError, ValueError):
    """A configuration file or option is invalid (names the key)."""

    exit_code = 2


class InputError(ViperError, ValueError):
    """User input (a file's content, a command-line value) is invalid."""

    exit_code = 2


class OutputError(ViperError, OSError):
    """An output file or folder cannot be written (missing folder, a folder in its place, read-only,
    full disk) or would replace an input or an existing file without ``--force``."""


class DemError(ViperError, OSError):
    """A DEM cannot be read or is unusable (unreadable, unknown CRS, all nodata...)."""


class NodataCandidatesError(DemError):
    """Every candidate node of a database to build lies on nodata: an error for one database, a
    void tile (left out of the index) in a tiled build."""


class DatabaseError(ViperError, OSError):
    """A skyline database is corrupt, of another format version, or built from another DEM."""


class EstimationError(ViperError, ValueError):
    """The estimator cannot produce an estimate from its input."""


class DeviceError(ViperError, OSError):
    """A device does not answer, answers wrongly or went away."""


class ProtocolError(ViperError, ValueError):
    """Bytes from a device do not follow its protocol."""


class LogError(ViperError, OSError):
    """A logbook (MCAP) cannot be written, read or recovered."""


class CalibrationError(ViperError, ValueError):
    """A calibration cannot be computed from its input."""


class ErrorPolicy(enum.Enum):
    """What a streaming reader does with a record it cannot use: raise (tests), log a warning and
    count it (daemons), or only count it (batch tools).  Whatever the policy, a bad record never
    becomes a value.  A reader that cannot find the next record after a bad one (a log file cut
    short) stops there under ``LOG`` and ``SKIP`` and says why."""

    RAISE = "raise"
    LOG = "log"
    SKIP = "skip"


E = TypeVar("E", bound=enum.Enum)


def enum_member(cls: type[E], name: str | E, what: str) -> E:
    """``name`` as a member of ``cls`` (a member passes as it is), or an :class:`InputError` naming
    ``what`` and every value ``cls`` holds."""
    if isinstance(name, cls):
        return name
    try:
        return cls(name)
    except ValueError:
        names = ", ".join(str(m.value) for m in cls)
        raise InputError(f"{what} {name!r} unknown; expected one of {names}") from None

"""Where the appliance's log messages go: stderr, with journal priorities under systemd, and one
progress bar (tqdm) for long commands, quiet when stderr is not a terminal.

Under systemd (``JOURNAL_STREAM`` names stderr), each line starts with its sd-daemon priority
(``<3>`` error, ``<4>`` warning, ``<6>`` info, ``<7>`` debug) so ``journalctl -p warning`` finds
the warnings; elsewhere the line is the message alone.  The CLI's results stay on stdout.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterable, Iterator
from typing import IO, Any, TypeVar

LEVELS = ("debug", "info", "warning", "error")
_PRIORITIES = ((logging.ERROR, 3), (logging.WARNING, 4), (logging.INFO, 6))
T = TypeVar("T")


def journal_priority(levelno: int) -> int:
    """The syslog priority of a logging level (3 error and above, 4 warning, 6 info, 7 debug)."""
    for threshold, priority in _PRIORITIES:
        if levelno >= threshold:
            return priority
    return 7


def stream_is_journal(stream: IO[str], environ: dict[str, str] | None = None) -> bool:
    """True when ``stream`` is the journal's stream of this service (``JOURNAL_STREAM=DEV:INODE``)."""
    value = (os.environ if environ is None else environ).get("JOURNAL_STREAM", "")
    dev, sep, inode = value.partition(":")
    if not sep:
        return False
    try:
        st = os.fstat(stream.fileno())
    except (OSError, ValueError, AttributeError):
        return False
    return f"{st.st_dev}:{st.st_ino}" == f"{dev}:{inode}"


class _StderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever ``sys.stderr`` is when a message comes (it may be replaced after setup)."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)


class JournalFormatter(logging.Formatter):
    """``<priority>message``: sd-daemon(3) prefixes that journald turns into the entry's priority."""

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{journal_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines() or [""])


def configure_logging(level: str = "info", stream: IO[str] | None = None,
                      environ: dict[str, str] | None = None) -> logging.Handler:
    """Send the ``appliance`` loggers at ``level`` and above to ``stream`` (stderr); returns the handler."""
    if level not in LEVELS:
        raise ValueError(f"log level {level!r}: expected one of {', '.join(LEVELS)}")
    out = sys.stderr if stream is None else stream
    handler: logging.StreamHandler[Any] = logging.StreamHandler(out) if stream is not None else _StderrHandler()
    journal = stream_is_journal(out, environ)
    handler.setFormatter(JournalFormatter("%(message)s") if journal else logging.Formatter("%(message)s"))
    root = logging.getLogger("appliance")
    for old in list(root.handlers):
        if getattr(old, "_viper", False):
            root.removeHandler(old)
    handler._viper = True  # type: ignore[attr-defined]
    root.addHandler(handler)
    root.setLevel(level.upper())
    return handler


def progress(items: Iterable[T], total: int | None = None, desc: str = "", unit: str = "it") -> Iterator[T]:
    """``items`` with a progress bar on stderr when it is a terminal (tqdm), else silently."""
    from tqdm import tqdm

    yield from tqdm(items, total=total, desc=desc, unit=unit, disable=not _stderr_is_terminal(), leave=False)


class ProgressCallback:
    """A ``(done, total, label)`` callback (as ``build_database`` takes) drawn with tqdm on a terminal."""

    def __init__(self, unit: str = "it") -> None:
        self._bar: Any = None
        self._unit = unit

    def __call__(self, done: int, total: int, label: str) -> None:
        if not _stderr_is_terminal():
            return
        from tqdm import tqdm

        if self._bar is None or self._bar.desc != label or self._bar.total != total:
            self.close()
            self._bar = tqdm(total=total, desc=label, unit=self._unit, leave=False)
        self._bar.update(done - self._bar.n)
        if done >= total:
            self.close()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    @staticmethod
    def write(text: str) -> None:
        """A result line on stdout, through the bar's own writer: the bar is lifted, the line printed
        and the bar redrawn below it, so that the line does not land on the bar."""
        from tqdm import tqdm  # tqdm loads only when a command reports progress

        tqdm.write(text, file=sys.stdout)


class StatusLine:
    """An ``on_status`` callback for sessions: each status is logged at debug level and, on a terminal,
    shown on one self-updating line (a tqdm bar counting the steps)."""

    def __init__(self, desc: str) -> None:
        self._desc = desc
        self._bar: Any = None
        self.steps = 0

    def __call__(self, text: str) -> None:
        self.steps += 1
        logging.getLogger("appliance.session").debug("%s: %s", self._desc, text)
        if self._bar is None and _stderr_is_terminal():
            from tqdm import tqdm

            self._bar = tqdm(desc=self._desc, unit="step", leave=False)
        if self._bar is not None:
            self._bar.set_postfix_str(text, refresh=False)
            self._bar.update(1)

    def __enter__(self) -> StatusLine:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def _stderr_is_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False

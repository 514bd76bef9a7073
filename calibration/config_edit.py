"""Format-preserving, atomic edits of TOML files (the configuration and the calibration files).

A calibration writes a few keys into one table of a TOML file and leaves every other byte as it
was: comments, key order, blank lines and the other tables.  The new text is checked (``validate``)
before anything touches the disk, and the file is replaced atomically
(:func:`appliance.atomic.write_text_atomic`: temporary file in the same folder, fsync, rename), so
on any error the original file is untouched.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import tomlkit
import tomlkit.exceptions
from tomlkit.items import Table

from appliance.atomic import write_text_atomic
from appliance.errors import ConfigError
from appliance.inputs import MAX_CONFIG_BYTES, NestingError, check_nesting, read_text_bounded


def read_toml_text(path: str | Path, *, must_exist: bool = True) -> str:
    """The file's text (UTF-8); ``""`` for a missing file when ``must_exist`` is false."""
    p = Path(path)
    try:
        text = read_text_bounded(p, MAX_CONFIG_BYTES, "configuration", ConfigError)
        check_nesting(text)
        return text
    except NestingError as exc:
        raise ConfigError(f"{p}: {exc}") from None
    except FileNotFoundError:
        if must_exist:
            raise ConfigError(f"{p}: file not found") from None
        return ""
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not UTF-8 text: {exc}") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read: {exc.strerror or exc}") from None


def with_table_values(
    text: str, table: str, values: Mapping[str, Any], *, source: str = "<toml>", remove: Iterable[str] = ()
) -> str:
    """``text`` with ``[table]`` keys set to ``values``; everything else kept byte for byte.

    ``table`` may be dotted (``"compass"`` or ``"drivers.compass"``); missing tables are appended.
    Existing keys keep their position and any trailing comment; new keys are added at the table's end.
    Keys named in ``remove`` (superseded ones) are deleted from the table when present.
    """
    try:
        doc = tomlkit.parse(text)
    except tomlkit.exceptions.ParseError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    container: Any = doc
    walked: list[str] = []
    for name in table.split("."):
        walked.append(name)
        if name not in container:
            container.add(name, tomlkit.table())
        container = container[name]
        if not isinstance(container, (Table, dict)):
            raise ConfigError(f"{source}: {'.'.join(walked)} is a {type(container).__name__}, not a table")
    for key, value in values.items():
        new = tomlkit.item(list(value) if isinstance(value, tuple) else value)
        if key in container:
            old = container.item(key) if hasattr(container, "item") else None
            comment = getattr(getattr(old, "trivia", None), "comment", "")
            container[key] = new
            if comment:
                container.item(key).trivia.comment = comment
                container.item(key).trivia.comment_ws = old.trivia.comment_ws  # type: ignore[union-attr]
        else:
            container[key] = new
    for key in remove:
        if key in container and key not in values:
            del container[key]
    return tomlkit.dumps(doc)


def update_toml_table(
    path: str | Path,
    table: str,
    values: Mapping[str, Any],
    *,
    must_exist: bool = True,
    validate: Callable[[str], None] | None = None,
    remove: Iterable[str] = (),
) -> str:
    """Set ``values`` in ``[table]`` of the TOML file ``path``, keeping the rest of it; returns the new text.

    ``validate`` receives the new text and raises (a ViperError) to refuse it; the file is then
    untouched.  A missing file is an error unless ``must_exist`` is false (it is then created).
    """
    p = Path(path)
    old = read_toml_text(p, must_exist=must_exist)
    new = with_table_values(old, table, values, source=str(p), remove=remove)
    if validate is not None:
        validate(new)
    write_text_atomic(p, new)
    return new


def significant(value: float, digits: int = 6) -> float:
    """``value`` rounded to ``digits`` significant digits (for readable TOML numbers)."""
    return float(f"{value:.{digits}g}")

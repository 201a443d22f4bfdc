"""TOML reading and writing with errors that name the file and field."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import tomli_w

from livebridge.atomic import write_bytes_atomically
from livebridge.errors import InputError, file_error

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file; a missing, unreadable, non-UTF-8 or malformed file raises :class:`InputError`. A UTF-8
    byte order mark (Windows Notepad writes one) is skipped."""
    path = Path(path)
    try:
        return tomllib.loads(path.read_bytes().decode("utf-8-sig"))
    except OSError as error:
        raise file_error(error, path) from None
    except UnicodeDecodeError as error:
        raise InputError(f"not UTF-8 text (byte {error.object[error.start:error.start + 1]!r} at offset "
                         f"{error.start})", path) from None
    except tomllib.TOMLDecodeError as error:
        raise InputError(f"not valid TOML ({error})", path) from None


def save_toml(path: str | Path, data: dict[str, Any]) -> None:
    """Write ``data`` as TOML, atomically (a crash never leaves half a file)."""
    write_bytes_atomically(path, tomli_w.dumps(data).encode(), "TOML file")


def require(table: dict[str, Any], key: str, kind: type | tuple[type, ...], path: str | Path,
            prefix: str = "") -> Any:
    """Return ``table[key]`` checked against ``kind``, or raise naming ``prefix.key``."""
    field = f"{prefix}.{key}" if prefix else key
    if key not in table:
        raise InputError("missing", path, field)
    value = table[key]
    if not isinstance(value, kind) or isinstance(value, bool) and bool not in _as_tuple(kind):
        names = " or ".join(k.__name__ for k in _as_tuple(kind))
        raise InputError(f"expected {names}, got {type(value).__name__} {value!r}", path, field)
    return value


def _as_tuple(kind: type | tuple[type, ...]) -> tuple[type, ...]:
    return kind if isinstance(kind, tuple) else (kind,)

"""Files written whole or not at all: to ``<name>.partial``, synced, then renamed over the target."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from livebridge.errors import InputError


def write_atomically(out: str | Path, write: Callable[[BinaryIO], None], what: str = "file",
                     like: str | Path | None = None) -> Path:
    """Call ``write(handle)`` on ``<out>.partial`` and rename it to ``out``.

    A crash never leaves half a file at ``out``, and a failed write leaves no ``.partial`` behind; an
    :class:`OSError` becomes an :class:`InputError` naming ``out`` ("cannot write the ``what``"). A symbolic
    link at ``out`` is followed, not replaced; the new file gets the permission bits of ``like`` (default: the
    file it replaces, if any).
    """
    out = Path(out)
    target = Path(os.path.realpath(out))
    partial = target.with_name(target.name + ".partial")
    like = Path(like) if like is not None else target
    try:
        with open(partial, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        if like.exists():
            shutil.copymode(like, partial)
        os.replace(partial, target)
    except OSError as error:
        raise InputError(f"cannot write the {what} ({error.strerror or error})", out) from None
    finally:
        partial.unlink(missing_ok=True)  # after a failure; gone already after the rename
    return out


def write_bytes_atomically(out: str | Path, data: bytes, what: str = "file", like: str | Path | None = None) -> Path:
    """:func:`write_atomically` of ``data``."""
    return write_atomically(out, lambda handle: handle.write(data), what, like)

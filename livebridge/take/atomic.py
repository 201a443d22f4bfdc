"""Files written whole or not at all: to ``<name>.partial``, synced, then renamed over the target."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from livebridge.errors import InputError


def write_atomically(out: str | Path, write: Callable[[BinaryIO], None], what: str = "file") -> Path:
    """Call ``write(handle)`` on ``<out>.partial`` and rename it to ``out``.

    A crash never leaves half a file at ``out``, and a failed write leaves no ``.partial`` behind; an
    :class:`OSError` becomes an :class:`InputError` naming ``out`` ("cannot write the ``what``").
    """
    out = Path(out)
    partial = out.with_name(out.name + ".partial")
    try:
        with open(partial, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(partial, out)
    except OSError as error:
        raise InputError(f"cannot write the {what} ({error.strerror or error})", out) from None
    finally:
        partial.unlink(missing_ok=True)  # after a failure; gone already after the rename
    return out

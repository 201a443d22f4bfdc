""".npz reading with errors that name the file and array: every array as plain numbers (no pickles), the file
closed on every path."""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from livebridge.errors import InputError, file_error

NPZ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError, RuntimeError)
"""What numpy and zipfile raise on a damaged ``.npz``: numpy takes a file that is neither a zip nor a ``.npy`` for a
pickle (ValueError, pickles refused), a damaged member fails its CRC or inflation (BadZipFile, zlib.error), and
zipfile refuses a member flagged as strongly encrypted (NotImplementedError) or as needing a password
(RuntimeError)."""


def read_npz(path: str | Path, what: str, keys: tuple[str, ...] | None = None,
             others: bool = False) -> dict[str, np.ndarray]:
    """The arrays ``keys`` of the ``.npz`` at ``path`` (default: all it has; with ``others``, every other one it
    has too), read into memory.

    A missing, unreadable, foreign or damaged file, or one without an array of ``keys``, raises
    :class:`InputError` naming the file (and the array missing or unreadable), and saying it is not a ``what``
    (``"livebridge take"``). numpy leaves the file open when its zip is damaged; it is opened here and closed
    whatever happens.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"is a directory, not a {what} .npz", path)
    try:
        handle = path.open("rb")
    except OSError as error:
        raise file_error(error, path) from None
    with handle:
        try:
            data = np.load(handle, allow_pickle=False)
        except NPZ_ERRORS as error:
            reason = error if zipfile.is_zipfile(path) else "not a zip archive, which a .npz is"
            raise InputError(f"not a {what} .npz: truncated, damaged or another kind of file ({reason!s:.80})",
                             path) from None
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise InputError(f"not a {what} .npz: a single array (.npy)", path)
        arrays = {}
        with data:
            for key in data.files if keys is None or others else [key for key in keys if key in data.files]:
                try:
                    arrays[key] = data[key]
                except NPZ_ERRORS as error:  # a damaged member, or an object array (pickles are never loaded)
                    raise InputError(f"cannot read the array: damaged or not plain numbers ({error!s:.60})", path,
                                     key) from None
    missing = [key for key in keys or () if key not in arrays]
    if missing:
        raise InputError(f"missing array {missing[0]!r}", path, missing[0])
    return arrays

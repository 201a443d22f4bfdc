"""Errors that name what is wrong with the user's input."""

from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """Bad input: names the file, the field (or device) and what is wrong.

    Parameters
    ----------
    message : str
        What is wrong, in words a user can act on.
    path : str or Path, optional
        The file (or device URL) the bad input came from.
    field : str, optional
        The dotted field inside that file, e.g. ``servo.jaw.max``.
    """

    def __init__(self, message: str, path: str | Path | None = None, field: str | None = None):
        self.message = message
        self.path = None if path is None else str(path)
        self.field = field
        where = ": ".join(part for part in (self.path, field) if part)
        super().__init__(f"{where}: {message}" if where else message)

    def __reduce__(self):  # from a worker process with its file and field, not only its text
        return type(self), (self.message, self.path, self.field)


def os_error_reason(error: OSError) -> str:
    """What an :class:`OSError` about a file or address means, in a few words (no errno, no path)."""
    import errno

    reasons = {
        errno.ENOENT: "file not found",
        errno.EISDIR: "is a directory, not a file",
        errno.ENOTDIR: "a part of the path is not a directory",
        errno.EACCES: "permission denied",
        errno.EPERM: "permission denied",
        errno.EEXIST: "already exists",
        errno.ENOSPC: "no space left on the device",
        errno.EROFS: "read-only file system",
        errno.EADDRINUSE: "address already in use (another program, or another livebridge, listens there)",
        errno.EADDRNOTAVAIL: "address not available on this machine",
    }
    return reasons.get(error.errno, error.strerror or str(error))


def file_error(error: OSError, path: str | Path | None = None) -> InputError:
    """An :class:`InputError` for an :class:`OSError` met while opening or reading ``path``."""
    return InputError(os_error_reason(error), path if path is not None else error.filename)

"""The ``livebridge`` command line.

Each command group lives in its own module of this package and is attached
here; heavy imports (OpenCV, scipy, hardware SDKs) happen inside the
commands, so ``livebridge --help`` stays fast and needs no device.

Errors meet the user in one place, :meth:`_Livebridge.invoke`: bad input
(:class:`~livebridge.errors.InputError`, a file that cannot be read, a port
in use) prints one ``Error:`` line naming the file, field, option or port;
anything else is a bug, reported in one line with the path of a file that
holds the full traceback. Ctrl-C outside a running pipeline exits with 130;
output whose reader went away (``livebridge ... | head -1``) ends the command
quietly with 141.
"""

from __future__ import annotations

import datetime
import json
import os
import sys
import tempfile
import traceback
import zipfile

import click

from livebridge import __version__
from livebridge.cli._attach import attach
from livebridge.errors import InputError, os_error_reason

# (module, attribute) of every command attached to the top-level group.
_COMMANDS = (
    ("livebridge.cli.basis", "basis"),
    ("livebridge.cli.markers", "markers"),
    ("livebridge.cli.landmarks", "landmarks"),
    ("livebridge.cli.retarget", "retarget"),
    ("livebridge.cli.calibrate", "calibrate"),
    ("livebridge.cli.cameras", "devices"),
    ("livebridge.cli.servo", "servo"),
    ("livebridge.cli.sim", "sim"),
    ("livebridge.cli.node", "node"),
    ("livebridge.cli.bench", "bench"),
    ("livebridge.cli.runtime", "run"),
    ("livebridge.cli.runtime", "demo"),
    ("livebridge.cli.take", "take"),
    ("livebridge.cli.play", "play"),
    ("livebridge.cli.solve", "solve"),
    ("livebridge.cli.process", "process"),
    ("livebridge.cli.markerless", "markerless"),
    ("livebridge.cli.character", "character"),
)
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report a command stopped by Ctrl-C
EXIT_OUTPUT_CLOSED = 141  # 128 + SIGPIPE, as shells report a command whose reader went away (`... | head`)


def user_error_message(error: BaseException) -> str | None:
    """One line saying what is wrong with the user's input, or None when ``error`` is a bug."""
    if isinstance(error, InputError):
        return str(error)
    if isinstance(error, UnicodeDecodeError):
        return f"not UTF-8 text (byte {error.object[error.start:error.start + 1]!r} at offset {error.start})"
    if isinstance(error, OSError) and error.errno is not None:
        where = error.filename if error.filename is not None else None
        return f"{where}: {os_error_reason(error)}" if where else os_error_reason(error)
    if isinstance(error, zipfile.BadZipFile):
        return f"not a zip (.npz) file ({error})"
    if isinstance(error, json.JSONDecodeError):
        return f"not valid JSON ({error})"
    return None


def write_crash_report(error: BaseException) -> str:
    """Write ``error``'s full traceback to a new file in the temp folder; returns its path."""
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    handle, path = tempfile.mkstemp(prefix=f"livebridge-crash-{stamp}-", suffix=".txt")
    with os.fdopen(handle, "w", encoding="utf-8") as stream:
        stream.write(f"livebridge {__version__}, Python {sys.version.split()[0]}\n")
        stream.write(f"command: {' '.join(sys.argv)}\n\n")
        stream.write("".join(traceback.format_exception(error)))
    return path


def _one_line(text: str, limit: int = 300) -> str:
    text = " ".join(text.split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _stdout_closed() -> bool:
    """Whether standard output is a pipe whose reader has gone (the kernel reports an error on its write end);
    then it is pointed at the null device, so that Python's own flush at exit does not fail again."""
    import select

    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a file: a test's captured output
        return False
    if not hasattr(select, "poll"):
        return False
    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    closed = any(event & select.POLLERR for _, event in poller.poll(0))
    if closed:
        os.dup2(os.open(os.devnull, os.O_WRONLY), fd)
    return closed


class _Livebridge(click.Group):
    """The top-level group; its :meth:`invoke` is the command line's one error boundary."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except KeyboardInterrupt:
            click.echo("\ninterrupted", err=True)
            ctx.exit(EXIT_INTERRUPTED)
        except Exception as error:  # the boundary: every failure becomes one line, bugs keep a traceback file
            if isinstance(error, BrokenPipeError) and _stdout_closed():
                ctx.exit(EXIT_OUTPUT_CLOSED)  # the reader of our output went away: quietly, as any Unix tool
            message = user_error_message(error)
            if message is None:
                path = write_crash_report(error)
                message = (f"internal error ({type(error).__name__}: {_one_line(str(error))}); "
                           f"full traceback written to {path}")
            raise click.ClickException(message) from None


@click.group(cls=_Livebridge, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="livebridge")
def main() -> None:
    """Live facial motion capture to muscle contractions and animatronics."""


attach(main, _COMMANDS)

"""The command line's parameter types and checks: every option is validated before a command does any work.

One small set, used by every command: finite numbers in a range (:class:`FiniteFloat`; click's
``FloatRange`` lets NaN and, without a bound, infinity through), counts (``click.IntRange`` with both
bounds), image sizes (:class:`Size`), ports (:class:`Port`), a server's bind host (:class:`BindHost`, local
unless ``--allow-remote``), a UDP destination (:class:`Destination`), input files and folders
(:class:`InputPath`), output files and folders (:class:`OutputFile`, :class:`NewFolder`; an existing file is
kept unless ``--force``), device URLs (:class:`CameraURL`), ``NAME=VALUE`` pairs (:class:`Named`), and the
checks of the servo commands whose ranges depend on the bus (:func:`inside`, :func:`positive`,
:func:`parse_addresses`).

A refusal is :class:`click.BadParameter` naming the option, so the user sees one ``Error:`` line and a
non-zero exit, and nothing has been opened, sent or written yet.
"""

from __future__ import annotations

import errno
import ipaddress
import math
import os
from pathlib import Path

import click

from livebridge.devices.url import parse_ranges
from livebridge.errors import InputError, os_error_reason

MAX_FRAMES = 10**9
"""The largest frame count an option accepts (about 100 days at 120 fps)."""


# ------------------------------------------------------------------------------------------------ numbers
class FiniteFloat(click.FloatRange):
    """A finite number in ``[low, high]`` (``low_open``/``high_open`` exclude that end)."""

    name = "number"

    def __init__(self, low: float | None = None, high: float | None = None, low_open: bool = False,
                 high_open: bool = False):
        super().__init__(low, high, min_open=low_open, max_open=high_open)

    def convert(self, value, param, ctx) -> float:
        number = click.FLOAT.convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value} is not a finite number", param, ctx)
        above = self.min is None or (number > self.min if self.min_open else number >= self.min)
        below = self.max is None or (number < self.max if self.max_open else number <= self.max)
        if not (above and below):
            self.fail(f"{value} is not in the range {self._describe_range().replace('x', 'value', 1)}", param, ctx)
        return number


PROBABILITY = FiniteFloat(0.0, 1.0)
SEED = click.IntRange(0, 2**32 - 1)  # numpy's and the simulators' seeds
FRAMES = click.IntRange(0, MAX_FRAMES)


class Size(click.ParamType):
    """``WxH`` -> ``(width, height)``, each a whole number in ``[low, high]`` pixels."""

    name = "WxH"

    def __init__(self, low: int, high: int):
        self.low, self.high = low, high

    def convert(self, value, param, ctx) -> tuple[int, int]:
        if isinstance(value, tuple):
            return value
        try:
            width, height = (int(v) for v in str(value).lower().split("x"))
        except ValueError:
            self.fail(f"expected WxH, e.g. 1280x800, got {value!r}", param, ctx)
        if not (self.low <= width <= self.high and self.low <= height <= self.high):
            self.fail(f"{value}: width and height must each be in {self.low}..{self.high} pixels", param, ctx)
        return width, height


# ------------------------------------------------------------------------------------------------ network
class Port(click.IntRange):
    """A TCP/UDP port, 1..65535 (0 too when ``any_free``: the system picks a free one)."""

    name = "port"

    def __init__(self, any_free: bool = False):
        super().__init__(0 if any_free else 1, 65535)


def bind_host_problem(host: str) -> str | None:
    """Why a server should not bind ``host`` without the user's say-so (None: it is a loopback address).

    Any other address (``0.0.0.0``, a LAN address, a name) lets other machines open the page.
    """
    name = host.strip().removeprefix("[").removesuffix("]").lower()
    if name == "localhost":
        return None
    try:
        if ipaddress.ip_address(name.split("%")[0]).is_loopback:
            return None
    except ValueError:
        pass
    return (f"{host!r} is not a loopback address: other machines could open the live face there; "
            f"add --allow-remote to serve it on {host!r} anyway")


def allow_remote_option(command):
    """``--allow-remote``: read before the other options (eager), so :class:`BindHost` can see it."""
    return click.option("--allow-remote", is_flag=True, is_eager=True,
                        help="Allow a render host that other machines can reach (not loopback).")(command)


class BindHost(click.ParamType):
    """An interface a server binds: a loopback address unless the command's ``--allow-remote`` is given."""

    name = "host"

    def convert(self, value, param, ctx) -> str:
        host = str(value).strip()
        if not host:
            self.fail("must name an interface, e.g. 127.0.0.1", param, ctx)
        problem = bind_host_problem(host)
        if problem is not None and not (ctx is not None and ctx.params.get("allow_remote")):
            self.fail(problem, param, ctx)
        return host


class Destination(click.ParamType):
    """``HOST:PORT`` of a UDP receiver (``[::1]:PORT`` for IPv6), checked by the VMC output's own rules."""

    name = "HOST:PORT"

    def convert(self, value, param, ctx) -> tuple[str, int]:
        if isinstance(value, tuple):
            return value
        host, _, port_text = str(value).rpartition(":")
        if not host or not port_text.isdigit():
            self.fail(f"expected HOST:PORT, got {value!r}", param, ctx)
        host = host.removeprefix("[").removesuffix("]")
        from livebridge.output.vmc import resolve_destination

        try:
            resolve_destination(host, int(port_text))
        except InputError as error:
            self.fail(f"{value}: {error.field}: {error.message}", param, ctx)
        return host, int(port_text)


# ------------------------------------------------------------------------------------------------ paths
def path_problem(path: Path, kind: str) -> str | None:
    """Why ``path`` cannot be read as a ``kind`` (``"file"``, ``"folder"`` or ``"any"``); None when it can."""
    if not path.exists():
        return "file not found" if kind != "folder" else "folder not found"
    if kind == "file" and path.is_dir():
        return "is a directory, not a file"
    if kind == "folder" and not path.is_dir():
        return "is a file, not a folder"
    if not os.access(path, os.R_OK):
        return "permission denied"
    return None


class InputPath(click.ParamType):
    """An existing, readable file (``kind="file"``), folder (``"folder"``) or either (``"any"``).

    ``builtins`` are names that stand for something shipped (``builtin``) and are passed through as text.
    """

    name = "path"

    def __init__(self, kind: str = "file", builtins: tuple[str, ...] = ()):
        self.kind, self.builtins = kind, builtins

    def convert(self, value, param, ctx):
        if value in self.builtins:
            return value
        path = Path(value)
        problem = path_problem(path, self.kind)
        if problem is not None:
            self.fail(f"{value}: {problem}", param, ctx)
        return path


def force_option(command):
    """``--force``: read before the other options (eager), so :class:`OutputFile` can see it."""
    return click.option("--force", is_flag=True, is_eager=True,
                        help="Overwrite output files that exist.")(command)


def overwrite_problem(path: Path) -> str | None:
    """Why a file cannot be written at ``path`` (its folder is missing, it is a folder); None when it can."""
    if not path.parent.is_dir():
        return f"the folder {str(path.parent)!r} does not exist; create it first"
    if path.is_dir():
        return "is a folder; give a file name"
    return None


def refuse_overwrite(paths, force: bool, option: str) -> None:
    """Raise :class:`click.BadParameter` naming ``option`` when one of ``paths`` exists and not ``force``."""
    for path in paths:
        if path.exists() and not force:
            raise click.BadParameter(f"{path} already exists; add --force to overwrite it", param_hint=option)


class OutputFile(click.ParamType):
    """A file a command writes: its folder exists, it is not a folder, and it exists only with ``--force``."""

    name = "file"

    def convert(self, value, param, ctx) -> Path:
        path = Path(value)
        problem = overwrite_problem(path)
        if problem is not None:
            self.fail(f"{value}: {problem}", param, ctx)
        if path.exists() and not (ctx is not None and ctx.params.get("force")):
            self.fail(f"{value} already exists; add --force to overwrite it", param, ctx)
        return path


class MeshFile(OutputFile):
    """A mesh a command writes (:class:`OutputFile`): OBJ, PLY or STL, by its suffix."""

    name = "mesh"
    suffixes = (".obj", ".ply", ".stl")

    def convert(self, value, param, ctx) -> Path:
        path = super().convert(value, param, ctx)
        if path.suffix.lower() not in self.suffixes:
            self.fail(f"{value}: a mesh is written as {', '.join(self.suffixes)}, not "
                      f"{path.suffix or '(no suffix)'!r}", param, ctx)
        return path


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pdf", ".svg", ".tif", ".tiff", ".webp")
"""What an image option writes (matplotlib picks the format by the suffix)."""


class ImageFile(OutputFile):
    """An image a command writes (:class:`OutputFile`) whose suffix names a format it can write."""

    name = "image"

    def convert(self, value, param, ctx) -> Path:
        path = super().convert(value, param, ctx)
        if path.suffix.lower() not in IMAGE_SUFFIXES:
            self.fail(f"{value}: an image is written as {', '.join(IMAGE_SUFFIXES)}, not "
                      f"{path.suffix or '(no suffix)'!r}", param, ctx)
        return path


class NewFolder(click.ParamType):
    """A folder a command creates: inside an existing folder, and not there yet (``exist_ok``: may be)."""

    name = "folder"

    def __init__(self, exist_ok: bool = False):
        self.exist_ok = exist_ok

    def convert(self, value, param, ctx) -> Path:
        path = Path(value)
        if not path.parent.is_dir():
            self.fail(f"{value}: the folder {str(path.parent)!r} does not exist; create it first", param, ctx)
        if path.exists() and not (self.exist_ok and path.is_dir()):
            self.fail(f"{value}: already exists; give a new folder", param, ctx)
        return path


# ------------------------------------------------------------------------------------------------ devices
class CameraURL(click.ParamType):
    """A camera source URL, parsed by the strict :class:`~livebridge.devices.url.DeviceURL` and its scheme
    known to the registry (the device itself is opened later)."""

    name = "URL"

    def convert(self, value, param, ctx) -> str:
        from livebridge.devices.registry import camera_schemes
        from livebridge.devices.url import DeviceURL

        try:
            url = DeviceURL.parse(str(value))
        except InputError as error:
            self.fail(str(error), param, ctx)
        if url.scheme not in camera_schemes():
            self.fail(f"{value}: unknown camera URL scheme {url.scheme!r}; known: "
                      f"{', '.join(sorted(camera_schemes()))}", param, ctx)
        return str(value)


class Named(click.ParamType):
    """``NAME=VALUE`` -> ``(name, value)``, the value converted by ``inner`` (a :class:`click.ParamType`)."""

    def __init__(self, inner: click.ParamType, what: str = "VALUE"):
        self.inner = inner
        self.name = f"NAME={what}"

    def convert(self, value, param, ctx) -> tuple[str, object]:
        if isinstance(value, tuple):
            return value
        name, sep, text = str(value).partition("=")
        if not sep or not name or not text:
            self.fail(f"expected {self.name}, got {value!r}", param, ctx)
        return name, self.inner.convert(text, param, ctx)


def unique_names(pairs, option: str) -> dict:
    """``(name, value)`` pairs as a dict; a name given twice is a :class:`click.BadParameter`."""
    out = {}
    for name, value in pairs:
        if name in out:
            raise click.BadParameter(f"name {name!r} given twice", param_hint=option)
        out[name] = value
    return out


# ------------------------------------------------------------------------------------------------ servo checks
def finite(value: float | None, option: str) -> float | None:
    """``value`` unchanged when it is finite (or None, an option not given)."""
    if value is not None and not math.isfinite(value):
        raise click.BadParameter(f"must be a finite number, got {value}", param_hint=option)
    return value


def inside(value: float | None, low: float, high: float, option: str, what: str) -> float | None:
    """``value`` unchanged when it is finite and in ``[low, high]`` (``what`` names that range in the error)."""
    finite(value, option)
    if value is not None and not low <= value <= high:
        raise click.BadParameter(f"{value:g} is outside {what} ({low:g}..{high:g})", param_hint=option)
    return value


def positive(value: float, option: str, unit: str) -> float:
    """``value`` unchanged when it is finite and > 0."""
    finite(value, option)
    if not value > 0:
        raise click.BadParameter(f"must be > 0 {unit}, got {value:g}", param_hint=option)
    return value


def parse_addresses(text: str, first: int, last: int, option: str) -> list[int]:
    """``"1-4,7"`` -> ``[1, 2, 3, 4, 7]``, every address in ``first..last`` and none twice
    (:func:`~livebridge.devices.url.parse_ranges`: bounds are checked before a range is expanded)."""
    try:
        return parse_ranges(text, first, last)
    except InputError as error:
        raise click.BadParameter(error.message, param_hint=option) from None


def bind_error(host: str, port: int) -> OSError | None:
    """The error binding a TCP server to ``host:port`` would meet now (None: it would bind; port 0 tests the host).

    A test bind made before a long set-up, so a port in use is reported at once; the server's own bind
    still reports it later (another program may take the port in between).
    """
    import socket

    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
    except (socket.gaierror, UnicodeError) as error:
        return OSError(errno.EADDRNOTAVAIL, f"cannot resolve {host!r} ({error})")
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is no clash
        try:
            probe.bind(address)
        except OSError as error:
            return error
    return None


def render_bind_problem(host: str, port: int) -> tuple[str, str] | None:
    """``("host" or "port", what is wrong)`` when the render server could not bind ``host:port`` now."""
    error = bind_error(host, port)
    if error is None:
        return None
    shown = f"[{host}]" if ":" in host else host
    which = "host" if error.errno in (errno.EADDRNOTAVAIL, errno.EAFNOSUPPORT) else "port"
    return which, f"render server {shown}:{port}: {os_error_reason(error)}"


def parse_correspond(pairs: tuple[str, ...]) -> dict[str, int]:
    """``NAME=VERTEX`` pairs (basis vertex indices)."""
    out = {}
    for pair in pairs:
        name, _, vertex = pair.partition("=")
        if not name or not vertex.strip().isdigit():
            raise click.BadParameter(f"expected NAME=VERTEX (a vertex index of the basis mesh), got {pair!r}",
                                     param_hint="--correspond")
        out[name] = int(vertex)
    return out

"""The camera-source interface and the URL registry that opens sources.

A camera source is anything with the :class:`CameraSource` protocol; real drivers and simulators are
equal implementations, chosen by URL in configuration:

=========================================================  ==================================================
``v4l2:///dev/video0?width=1280&height=720&fps=60&fourcc=MJPG&exposure_us=2000&gain=0``  a V4L2 camera
``depthai://DEVICE_ID/CAM_B?fps=60&exposure_us=2000&iso=400``  one mono camera of an OAK (``DEVICE_ID`` may be
                                                           ``any``; no socket: both mono cameras)
``replay://PATH?realtime=0``                               a recorded take (see :mod:`livebridge.capture.replay`)
``sim://rig?cameras=4&seed=1&fps=60&noise=2``              the simulated rig (one source per camera)
=========================================================  ==================================================

:func:`open_sources` returns every source a URL names (a simulated rig or an OAK yields several);
:func:`open_source` insists on exactly one. Hardware SDKs are imported only when their scheme is opened.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, runtime_checkable
from urllib.parse import parse_qs, urlsplit

from livebridge.capture.frame import Frame
from livebridge.errors import InputError

if TYPE_CHECKING:
    from livebridge.calibration.cameras import Camera


@dataclass(frozen=True)
class Capabilities:
    """What a camera source can do.

    Attributes
    ----------
    size : tuple of int
        Image ``(width, height)`` actually delivered.
    fps : float
        Frame rate actually configured (NaN when unknown).
    manual_exposure : bool
        True when :meth:`CameraSource.set_exposure` can set a manual exposure.
    exposure_range_us : tuple of float
        ``(min, max)`` manual exposure in microseconds (NaN, NaN when unknown).
    gain_range : tuple of float
        ``(min, max)`` gain or ISO (NaN, NaN when unknown).
    hardware_sync : bool
        True when frames of the source's ``sync_domain`` are triggered together.
    formats : tuple of str
        Pixel formats or other modes the device offers (informational).
    """

    size: tuple[int, int]
    fps: float = math.nan
    manual_exposure: bool = False
    exposure_range_us: tuple[float, float] = (math.nan, math.nan)
    gain_range: tuple[float, float] = (math.nan, math.nan)
    hardware_sync: bool = False
    formats: tuple[str, ...] = field(default_factory=tuple)


@dataclass(frozen=True)
class ExposureSetting:
    """The exposure a source actually applied (what it read back, not what was asked).

    Attributes
    ----------
    manual : bool
    exposure_us : float
        NaN when the source cannot tell.
    gain : float
        NaN when the source cannot tell.
    """

    manual: bool
    exposure_us: float = math.nan
    gain: float = math.nan


@runtime_checkable
class CameraSource(Protocol):
    """One camera. Life cycle: ``start()`` -> ``read()`` ... -> ``stop()`` (or use it as a context manager).

    ``read(timeout)`` returns the next frame, or None when none came within ``timeout`` seconds or the
    source has ended (``ended`` is then True and ``error`` says why, e.g. the camera was unplugged).
    """

    source_id: str

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def __enter__(self) -> CameraSource: ...

    def __exit__(self, *exc) -> None: ...

    def read(self, timeout: float | None = None) -> Frame | None: ...

    def set_exposure(self, manual: bool, exposure_us: float | None = None,
                     gain: float | None = None) -> ExposureSetting: ...

    @property
    def capabilities(self) -> Capabilities: ...

    @property
    def ended(self) -> bool: ...

    @property
    def error(self) -> str | None: ...


class SourceWrapper:
    """A camera source that wraps another and adds to ``read``; everything else is the inner source's.

    The runtime stacks these (detection on the reader thread, recording, unpaced lockstep); subclasses
    override ``read`` (and ``stop`` where they must).
    """

    def __init__(self, source):
        self.source = source
        self.source_id = source.source_id

    def __getattr__(self, name):
        return getattr(self.source, name)

    def start(self) -> None:
        self.source.start()

    def stop(self) -> None:
        self.source.stop()

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def read(self, timeout: float | None = None):
        return self.source.read(timeout)


class SourceBase:
    """Context-manager plumbing shared by the implementations (subclasses define start/stop)."""

    source_id: str = ""
    _ended: bool = False
    _error: str | None = None

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def ended(self) -> bool:
        return self._ended

    @property
    def error(self) -> str | None:
        return self._error

    @property
    def calibration(self) -> Camera | None:
        """The camera's own calibration when the source knows it (a simulated camera); None otherwise."""
        return None

    def _end(self, error: str | None) -> None:
        self._ended = True
        if error and self._error is None:
            self._error = error


# ---------------------------------------------------------------------------------------------- URLs

@dataclass(frozen=True)
class SourceURL:
    """A parsed source URL: ``scheme://netloc/path?key=value&...``."""

    url: str
    scheme: str
    netloc: str
    path: str
    query: dict[str, str]

    @classmethod
    def parse(cls, url: str) -> SourceURL:
        parts = urlsplit(url)
        if not parts.scheme:
            raise InputError("a camera URL needs a scheme (v4l2://, depthai://, replay://, sim://)", url)
        query = {}
        for key, values in parse_qs(parts.query, keep_blank_values=True).items():
            if len(values) > 1:
                raise InputError("parameter given twice", url, key)
            query[key] = values[0]
        return cls(url, parts.scheme.lower(), parts.netloc, parts.path, query)

    def take(self, key: str, kind: type, default=None):
        """Pop-like typed access: the value of ``key`` converted to ``kind`` (bool accepts 0/1/true/false)."""
        if key not in self.query:
            return default
        raw = self.query[key]
        try:
            if kind is bool:
                lowered = raw.lower()
                if lowered in ("1", "true", "yes", "on"):
                    return True
                if lowered in ("0", "false", "no", "off"):
                    return False
                raise ValueError(raw)
            return kind(raw)
        except ValueError:
            raise InputError(f"expected {kind.__name__}, got {raw!r}", self.url, key) from None

    def check_known(self, known: set[str]) -> None:
        """Raise on a parameter the scheme does not understand (a typo must not be silently ignored)."""
        unknown = sorted(set(self.query) - known)
        if unknown:
            raise InputError(f"unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}",
                             self.url, unknown[0])


_OPENERS: dict[str, Callable[[SourceURL], list]] = {}


def register_scheme(scheme: str, opener: Callable[[SourceURL], list]) -> None:
    """Register ``opener(parsed_url) -> list of sources`` for a URL scheme."""
    _OPENERS[scheme.lower()] = opener


def _open_v4l2(url: SourceURL) -> list:
    from livebridge.drivers.v4l2 import open_url

    return open_url(url)


def _open_depthai(url: SourceURL) -> list:
    from livebridge.drivers.depthai import open_url

    return open_url(url)


def _open_replay(url: SourceURL) -> list:
    from livebridge.capture.replay import open_url

    return open_url(url)


def _open_sim(url: SourceURL) -> list:
    from livebridge.simulators.rig import open_url

    return open_url(url)


for _scheme, _opener in (("v4l2", _open_v4l2), ("depthai", _open_depthai), ("replay", _open_replay),
                         ("sim", _open_sim)):
    register_scheme(_scheme, _opener)


def open_sources(url: str) -> list:
    """Every camera source the URL names, not started yet.

    Parameters
    ----------
    url : str
        See the module docstring.

    Returns
    -------
    list of CameraSource
    """
    parsed = SourceURL.parse(url)
    opener = _OPENERS.get(parsed.scheme)
    if opener is None:
        raise InputError(f"unknown camera scheme {parsed.scheme!r}; known: {', '.join(sorted(_OPENERS))}", url)
    return opener(parsed)


def open_source(url: str):
    """The one camera source the URL names (raises when it names several, e.g. a whole simulated rig)."""
    sources = open_sources(url)
    if len(sources) != 1:
        raise InputError(f"names {len(sources)} cameras; use open_sources() or pick one camera", url)
    return sources[0]

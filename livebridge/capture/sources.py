"""The camera-source interface: what every camera (real driver, replay or simulator) implements.

A camera source is anything with the :class:`CameraSource` protocol; real drivers and simulators are
equal implementations, chosen by URL in configuration (the schemes and their openers:
:mod:`livebridge.devices.registry`). :class:`SourceBase` is the plumbing the implementations share,
:class:`SourceWrapper` the base of the runtime's wrappers around a source.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, runtime_checkable

from livebridge.capture.frame import Frame

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
    images : bool
        True when frames carry the camera's full images; False when they carry the markers' centroids
        detected at the camera and no pixels, or a thumbnail (a camera node without ``images=full``).
    """

    size: tuple[int, int]
    fps: float = math.nan
    manual_exposure: bool = False
    exposure_range_us: tuple[float, float] = (math.nan, math.nan)
    gain_range: tuple[float, float] = (math.nan, math.nan)
    hardware_sync: bool = False
    formats: tuple[str, ...] = field(default_factory=tuple)
    images: bool = True


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
    realtime: bool
    """True when frames come at the camera's own pace (hardware, a paced replay or simulator); False when the
    source delivers the next frame as soon as it is asked (an unpaced replay or simulator)."""

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

    @property
    def calibration(self) -> Camera | None:
        """This camera as the source knows it (simulated, recorded with a take, factory-calibrated);
        None when unknown."""

    def status_text(self) -> str | None:
        """What the source adds to the live status line (a camera node: its clock offset and jitter, or
        ``lost``), or None for nothing."""

    def detect_with(self, config) -> None:
        """The host's marker-detection parameters (:class:`~livebridge.reconstruct.detect.DetectConfig`), for
        a source that detects where it films (a camera node); others detect nothing and ignore them."""

    def detect_board_with(self, board) -> None:
        """Calibration: a source that can detect the board where it films (a camera node) does, and its
        frames carry the corners (``Frame.board_corners``); others ignore it."""


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

    def status_text(self) -> str | None:
        return self.source.status_text()

    def detect_with(self, config) -> None:
        self.source.detect_with(config)

    def detect_board_with(self, board) -> None:
        self.source.detect_board_with(board)


class SourceBase:
    """Context-manager plumbing shared by the implementations (subclasses define start/stop)."""

    source_id: str = ""
    realtime: bool = True
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
        """None: a source that knows its camera's calibration overrides this."""
        return None

    def status_text(self) -> str | None:
        """None: a source with something to say in the status line overrides this."""
        return None

    def detect_with(self, config) -> None:
        """Nothing: the host detects in this source's images."""

    def detect_board_with(self, board) -> None:
        """Nothing: the host detects the board in this source's images."""

    def _end(self, error: str | None) -> None:
        self._ended = True
        if error and self._error is None:
            self._error = error

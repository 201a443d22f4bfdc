"""V4L2 cameras (Linux webcams, machine-vision USB cameras) through OpenCV's ``CAP_V4L2`` backend.

Configuration order matters to V4L2 drivers: FOURCC, then frame size, then frame rate; every value is read
back, because cameras silently pick the nearest mode they support. Exposure uses the raw V4L2 values
that OpenCV passes through: ``CAP_PROP_AUTO_EXPOSURE`` 1 = manual, 3 = auto (aperture priority), and
``CAP_PROP_EXPOSURE`` in units of 100 µs (``exposure_time_absolute``). The driver buffer holds 1–2
frames, so a frame is never older than that.

Raw buffers are fetched without OpenCV's colour conversion (``CAP_PROP_CONVERT_RGB = 0``) and turned into
grayscale directly: MJPG is decoded straight to luminance (``cv2.imdecode(..., IMREAD_GRAYSCALE)``), YUYV
keeps its Y bytes, GREY/Y8 passes through, Y16 keeps its high byte.

A grab thread per camera keeps only the newest frames (bounded queue). Timestamps are the kernel's buffer
times (``CAP_PROP_POS_MSEC``, ``CLOCK_MONOTONIC`` on UVC) when plausible, else host time at grab; either
way half the exposure is subtracted to land mid-exposure. A camera that stops delivering (unplugged,
device node gone, repeated grab failures) ends the source with ``error`` set; ``read`` then returns None.

:func:`list_devices` enumerates ``/dev/video*`` with their ``/dev/v4l/by-id`` names and formats through
the V4L2 ioctls directly (no OpenCV), for ``livebridge devices``.
"""

from __future__ import annotations

import fcntl
import glob
import math
import os
import struct
import threading
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from livebridge.capture.frame import Frame
from livebridge.capture.queue import NewestQueue
from livebridge.capture.sources import Capabilities, ExposureSetting, SourceBase
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError

AUTO_EXPOSURE_MANUAL = 1
AUTO_EXPOSURE_AUTO = 3
EXPOSURE_UNIT_US = 100.0
MAX_GRAB_FAILURES = 5


def fourcc_code(text: str) -> int:
    """FOURCC string (``MJPG``) to OpenCV's integer code."""
    text = (text + "    ")[:4]
    return cv2.VideoWriter_fourcc(*text)


def fourcc_text(code: float) -> str:
    """OpenCV's integer FOURCC (as ``cap.get`` returns it) to a string; ``''`` when unknown."""
    code = int(code)
    if code <= 0:
        return ""
    return "".join(chr((code >> (8 * k)) & 0xFF) for k in range(4)).strip("\x00 ")


def to_gray(raw: np.ndarray, fourcc: str, size: tuple[int, int]) -> np.ndarray | None:
    """One grabbed buffer to a grayscale image.

    Parameters
    ----------
    raw : ndarray
        What ``VideoCapture.retrieve`` returned: a byte buffer (``CONVERT_RGB`` off, shape (1, n) or (n,)),
        a BGR image (height, width, 3), or a grayscale image (height, width).
    fourcc : str
        Pixel format the camera accepted (``MJPG``, ``YUYV``, ``GREY``, ``Y16``, ...).
    size : tuple of int
        ``(width, height)`` the camera accepted.

    Returns
    -------
    ndarray of uint8, shape (height, width), or None when the buffer cannot be decoded (corrupt JPEG).
    """
    width, height = size
    if raw.ndim == 3 and raw.shape[2] == 3:
        return cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY)
    if raw.ndim == 3 and raw.shape[2] == 2:  # YUYV as (h, w, 2)
        return np.ascontiguousarray(raw[:, :, 0])
    if raw.ndim == 2 and raw.shape == (height, width) and raw.dtype == np.uint8 and fourcc not in ("MJPG", "JPEG"):
        return raw
    data = np.ascontiguousarray(raw).reshape(-1).view(np.uint8)
    fourcc = fourcc.upper()
    if fourcc in ("MJPG", "JPEG"):
        return cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
    if fourcc in ("YUYV", "YUY2") and data.size >= width * height * 2:
        return data[: width * height * 2].reshape(height, width * 2)[:, 0::2].copy()
    if fourcc == "UYVY" and data.size >= width * height * 2:
        return data[: width * height * 2].reshape(height, width * 2)[:, 1::2].copy()
    if fourcc in ("GREY", "Y800", "Y8  ", "Y8") and data.size >= width * height:
        return data[: width * height].reshape(height, width).copy()
    if fourcc in ("Y16", "Y16 ") and data.size >= width * height * 2:
        return (data[: width * height * 2].view("<u2").reshape(height, width) >> 8).astype(np.uint8)
    if raw.ndim == 2 and raw.shape == (height, width):
        return raw.astype(np.uint8)
    return None


def _open_capture(device: str):
    index = device
    if isinstance(device, str) and device.isdigit():
        index = int(device)
    return cv2.VideoCapture(index, cv2.CAP_V4L2)


class V4L2Source(SourceBase):
    """One V4L2 camera (see the module docstring).

    Parameters
    ----------
    device : str
        ``/dev/video0``, a ``/dev/v4l/by-id/...`` link, or an index.
    width, height : int, optional
    fps : float, optional
    fourcc : str
        Requested pixel format; ``MJPG`` by default (most USB cameras reach full rate only in MJPG).
    exposure_us : float, optional
        Manual exposure; None keeps the camera's setting.
    gain : float, optional
    buffer_size : int
        Driver buffers, 1 or 2.
    source_id : str, optional
        Name of the camera in the rig; default the device path.
    capture_factory : callable, optional
        ``factory(device) -> VideoCapture``-like object; default OpenCV with ``CAP_V4L2``. Tests pass a fake
        or OpenCV's image-sequence backend.
    queue_size : int
        Frames kept for ``read`` (the newest win).
    """

    def __init__(self, device: str, width: int | None = None, height: int | None = None, fps: float | None = None,
                 fourcc: str = "MJPG", exposure_us: float | None = None, gain: float | None = None,
                 buffer_size: int = 1, source_id: str | None = None, capture_factory=None, queue_size: int = 2):
        if buffer_size not in (1, 2):
            raise InputError(f"buffer_size must be 1 or 2, got {buffer_size}", device, "buffer")
        self.device = str(device)
        self.source_id = source_id or self.device
        self.requested = {"width": width, "height": height, "fps": fps, "fourcc": fourcc.upper()}
        self._initial_exposure = (exposure_us, gain)
        self.buffer_size = buffer_size
        self._factory = capture_factory or _open_capture
        self._cap = None
        self._lock = threading.Lock()
        self._queue: NewestQueue[Frame] = NewestQueue(queue_size)
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self.fourcc = ""
        self.size = (0, 0)
        self.fps = math.nan
        self.exposure = ExposureSetting(False)
        self.timestamp_source = "unknown"
        self.frames_grabbed = 0
        self.decode_failures = 0
        self._node_existed = False

    # ------------------------------------------------------------------------ life cycle
    def start(self) -> None:
        cap = self._factory(self.device)
        if cap is None or not cap.isOpened():
            raise InputError("cannot open the camera (missing, busy, or not a capture device)", self.device)
        self._cap = cap
        self._node_existed = os.path.exists(self.device)
        self._ended, self._error = False, None
        self._configure()
        exposure_us, gain = self._initial_exposure
        if exposure_us is not None or gain is not None:
            self.set_exposure(exposure_us is not None, exposure_us, gain)
        else:
            self.exposure = self._read_exposure()
        self._running.set()
        self._thread = threading.Thread(target=self._grab_loop, name=f"grab {self.source_id}", daemon=True)
        self._thread.start()

    def _configure(self) -> None:
        cap, want = self._cap, self.requested
        # order matters to V4L2: pixel format, then size, then rate
        if want["fourcc"]:
            cap.set(cv2.CAP_PROP_FOURCC, fourcc_code(want["fourcc"]))
        if want["width"]:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, want["width"])
        if want["height"]:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, want["height"])
        if want["fps"]:
            cap.set(cv2.CAP_PROP_FPS, want["fps"])
        cap.set(cv2.CAP_PROP_BUFFERSIZE, self.buffer_size)
        cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        # what the camera accepted
        self.fourcc = fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)) or want["fourcc"]
        self.size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        self.fps = fps if fps > 0 else math.nan

    def stop(self) -> None:
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        with self._lock:
            if self._cap is not None:
                self._cap.release()
                self._cap = None
        self._end(None)

    # ------------------------------------------------------------------------ frames
    def read(self, timeout: float | None = None) -> Frame | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            frame = self._queue.get(0.05 if deadline is None else max(0.0, min(0.05, deadline - time.monotonic())))
            if frame is not None:
                return frame
            if self._ended or (deadline is not None and time.monotonic() >= deadline):
                return None

    def _gone(self) -> bool:
        """The device node existed at start and has disappeared (USB unplug)."""
        return self._node_existed and not os.path.exists(self.device)

    def _grab_loop(self) -> None:
        failures = 0
        seq = 0
        while self._running.is_set():
            with self._lock:
                if self._cap is None:
                    break
                ok = self._cap.grab()
                t_host = time.monotonic()
                raw = None
                kernel_ms = math.nan
                if ok:
                    ok, raw = self._cap.retrieve()
                    kernel_ms = float(self._cap.get(cv2.CAP_PROP_POS_MSEC))
                exposure_us = self.exposure.exposure_us
            if not ok or raw is None:
                failures += 1
                if self._gone():
                    self._fail(f"{self.device}: camera unplugged (device node gone)")
                    break
                if failures >= MAX_GRAB_FAILURES:
                    self._fail(f"{self.device}: camera stopped delivering ({failures} failed grabs)")
                    break
                time.sleep(0.01)
                continue
            failures = 0
            image = to_gray(raw, self.fourcc, self.size)
            if image is None:
                self.decode_failures += 1
                continue
            self.frames_grabbed += 1
            t_end = self._timestamp(kernel_ms, t_host)
            half = 0.5 * exposure_us * 1e-6 if math.isfinite(exposure_us) else 0.0
            frame = Frame(image, t_end - half, seq, self.source_id, exposure_us, self.exposure.gain, self.source_id)
            seq += 1
            self._queue.put(frame)

    def _timestamp(self, kernel_ms: float, t_host: float) -> float:
        """Kernel buffer time on the monotonic clock when plausible (within 1 s before the grab), else host time."""
        if math.isfinite(kernel_ms) and kernel_ms > 0:
            kernel = kernel_ms / 1000.0
            if 0.0 <= t_host - kernel < 1.0:
                self.timestamp_source = "kernel"
                return kernel
        self.timestamp_source = "host"
        return t_host

    def _fail(self, message: str) -> None:
        self._end(message)
        self._running.clear()

    # ------------------------------------------------------------------------ controls
    def _read_exposure(self) -> ExposureSetting:
        cap = self._cap
        auto = cap.get(cv2.CAP_PROP_AUTO_EXPOSURE)
        exposure = cap.get(cv2.CAP_PROP_EXPOSURE)
        gain = cap.get(cv2.CAP_PROP_GAIN)
        return ExposureSetting(int(auto) == AUTO_EXPOSURE_MANUAL,
                               exposure * EXPOSURE_UNIT_US if exposure > 0 else math.nan,
                               gain if gain >= 0 else math.nan)

    def set_exposure(self, manual: bool, exposure_us: float | None = None, gain: float | None = None):
        """Manual (``exposure_us`` in µs, sent in 100 µs units) or automatic exposure; returns the read-back."""
        if self._cap is None:
            raise RuntimeError(f"{self.source_id}: set_exposure() before start()")
        with self._lock:
            cap = self._cap
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, AUTO_EXPOSURE_MANUAL if manual else AUTO_EXPOSURE_AUTO)
            if manual and exposure_us is not None:
                cap.set(cv2.CAP_PROP_EXPOSURE, max(1, round(exposure_us / EXPOSURE_UNIT_US)))
            if gain is not None:
                cap.set(cv2.CAP_PROP_GAIN, gain)
            self.exposure = self._read_exposure()
        return self.exposure

    @property
    def frames_dropped(self) -> int:
        """Grabbed frames dropped because ``read`` had not taken the older ones (the newest win)."""
        return self._queue.dropped

    @property
    def capabilities(self) -> Capabilities:
        formats = ()
        if self.device.startswith("/dev/"):
            try:
                formats = tuple(f.fourcc for f in query_formats(self.device))
            except OSError:
                formats = ()
        return Capabilities(size=self.size, fps=self.fps, manual_exposure=True, hardware_sync=False,
                            formats=formats or ((self.fourcc,) if self.fourcc else ()))


def open_url(url: DeviceURL) -> list[V4L2Source]:
    """``v4l2:///dev/video0?width=1280&height=720&fps=60&fourcc=MJPG&exposure_us=2000&gain=0&buffer=1&name=cam0``."""
    url.check_known({"width", "height", "fps", "fourcc", "exposure_us", "gain", "buffer", "name"})
    device = url.path if not url.netloc else url.netloc + url.path
    if not device:
        raise InputError("v4l2:// needs a device, e.g. v4l2:///dev/video0", url.url)
    return [V4L2Source(device, url.take("width", int), url.take("height", int), url.take("fps", float),
                       url.query.get("fourcc", "MJPG"), url.take("exposure_us", float), url.take("gain", float),
                       url.take("buffer", int, 1), url.query.get("name"))]


# ------------------------------------------------------------------------------------ device listing

def _ioc(direction: int, number: int, size: int) -> int:
    return (direction << 30) | (size << 16) | (ord("V") << 8) | number


_CAP = struct.Struct("16s32s32sIII12x")  # v4l2_capability, 104 bytes
_FMTDESC = struct.Struct("III32sII12x")  # v4l2_fmtdesc, 64 bytes
_FRMSIZE = struct.Struct("III6I8x")  # v4l2_frmsizeenum, 44 bytes
_FRMIVAL = struct.Struct("IIIII6I8x")  # v4l2_frmivalenum, 52 bytes
VIDIOC_QUERYCAP = _ioc(2, 0, _CAP.size)
VIDIOC_ENUM_FMT = _ioc(3, 2, _FMTDESC.size)
VIDIOC_ENUM_FRAMESIZES = _ioc(3, 74, _FRMSIZE.size)
VIDIOC_ENUM_FRAMEINTERVALS = _ioc(3, 75, _FRMIVAL.size)
V4L2_CAP_VIDEO_CAPTURE = 0x1
V4L2_CAP_DEVICE_CAPS = 0x80000000
V4L2_BUF_TYPE_VIDEO_CAPTURE = 1


@dataclass(frozen=True)
class V4L2Format:
    """One pixel format: FOURCC, description and ``(width, height, max fps)`` modes (discrete sizes only)."""

    fourcc: str
    description: str
    modes: tuple[tuple[int, int, float], ...] = ()


@dataclass(frozen=True)
class V4L2Device:
    """A V4L2 capture node."""

    path: str
    card: str
    driver: str
    bus: str
    by_id: tuple[str, ...] = ()
    formats: tuple[V4L2Format, ...] = field(default_factory=tuple)


def _text(raw: bytes) -> str:
    return raw.split(b"\x00", 1)[0].decode("utf-8", "replace")


def query_formats(path: str) -> list[V4L2Format]:
    """Pixel formats and discrete modes of a capture node (``VIDIOC_ENUM_FMT`` and friends)."""
    formats = []
    with open(path, "rb", buffering=0) as device:
        for index in range(64):
            buffer = bytearray(_FMTDESC.pack(index, V4L2_BUF_TYPE_VIDEO_CAPTURE, 0, b"", 0, 0))
            try:
                fcntl.ioctl(device, VIDIOC_ENUM_FMT, buffer)
            except OSError:
                break
            _, _, _, description, pixel_format, _ = _FMTDESC.unpack(buffer)
            modes = []
            for size_index in range(64):
                sizes = bytearray(_FRMSIZE.pack(size_index, pixel_format, 0, *([0] * 6)))
                try:
                    fcntl.ioctl(device, VIDIOC_ENUM_FRAMESIZES, sizes)
                except OSError:
                    break
                values = _FRMSIZE.unpack(sizes)
                if values[2] != 1:  # not discrete: report the largest size only
                    modes.append((values[4], values[7], math.nan))  # stepwise: max width, max height
                    break
                width, height = values[3], values[4]
                best = math.nan
                for rate_index in range(32):
                    rates = bytearray(_FRMIVAL.pack(rate_index, pixel_format, width, height, 0, *([0] * 6)))
                    try:
                        fcntl.ioctl(device, VIDIOC_ENUM_FRAMEINTERVALS, rates)
                    except OSError:
                        break
                    numerator, denominator = _FRMIVAL.unpack(rates)[5:7]
                    if numerator:
                        best = max(best, denominator / numerator) if math.isfinite(best) else denominator / numerator
                modes.append((width, height, best))
            formats.append(V4L2Format(fourcc_text(pixel_format), _text(description), tuple(modes)))
    return formats


def list_devices(dev: str = "/dev") -> list[V4L2Device]:
    """V4L2 capture nodes (metadata-only nodes are left out), with their by-id links and formats."""
    by_id: dict[str, list[str]] = {}
    for link in glob.glob(os.path.join(dev, "v4l", "by-id", "*")):
        by_id.setdefault(os.path.realpath(link), []).append(link)
    found = []
    for path in sorted(glob.glob(os.path.join(dev, "video*")), key=lambda p: (len(p), p)):
        try:
            with open(path, "rb", buffering=0) as device:
                buffer = bytearray(_CAP.size)
                fcntl.ioctl(device, VIDIOC_QUERYCAP, buffer)
        except OSError:
            continue
        driver, card, bus, _, capabilities, device_caps = _CAP.unpack(buffer)
        caps = device_caps if capabilities & V4L2_CAP_DEVICE_CAPS else capabilities
        if not caps & V4L2_CAP_VIDEO_CAPTURE:
            continue
        try:
            formats = tuple(query_formats(path))
        except OSError:
            formats = ()
        found.append(V4L2Device(path, _text(card), _text(driver), _text(bus),
                                tuple(sorted(by_id.get(os.path.realpath(path), []))), formats))
    return found


def describe(device: V4L2Device) -> str:
    """Human-readable lines for ``livebridge devices``."""
    lines = [f"{device.path}  {device.card} ({device.driver}, {device.bus})"]
    lines += [f"    by-id: {link}" for link in device.by_id]
    for fmt in device.formats:
        modes = ", ".join(f"{w}x{h}" + (f"@{fps:g}" if math.isfinite(fps) else "") for w, h, fps in fmt.modes[:8])
        more = f" (+{len(fmt.modes) - 8} more)" if len(fmt.modes) > 8 else ""
        lines.append(f"    {fmt.fourcc:4s} {fmt.description}: {modes}{more}")
    return "\n".join(lines)


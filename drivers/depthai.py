"""Luxonis OAK devices through the DepthAI v3 API (``depthai`` is imported only here).

An :class:`OakDevice` runs one pipeline on one device: a ``node.Camera`` per board socket, built with
``Camera.build(socket, sensorFps=fps)``, each with one grayscale output (``requestOutput(size,
ImgFrame.Type.GRAY8, fps=fps)``) read through a small non-blocking output queue, and a control input
queue for exposure. The two global-shutter mono cameras of an OAK-D (``CAM_B``, ``CAM_C``) are exposed
together by the hardware and number their frames alike, so they share one ``sync_domain``
(``oak:<device id>``). Manual exposure and ISO go in as the cameras' initial control and later as
``CameraControl`` messages. Where the device has IR drivers the flood light is switched on and the dot
projector off (both configurable). Several devices run side by side, one :class:`OakDevice` each.

Timestamps: ``ImgFrame.getTimestamp(CameraExposureOffset.MIDDLE)`` is the device clock already mapped
by DepthAI's time sync onto the host's ``steady_clock`` (``CLOCK_MONOTONIC`` = ``time.monotonic`` on
Linux), at mid-exposure.

The device's factory calibration converts to a :class:`~livebridge.calibration.cameras.CameraGroup`
(:func:`calibration_from_handler`, world frame = the first socket's camera, mm) and can be saved as a
livebridge calibration file (:func:`export_calibration`).
"""

from __future__ import annotations

import datetime
import math
import os
import threading

import cv2
import depthai as dai
import numpy as np

from livebridge.calibration.cameras import Camera, CameraGroup
from livebridge.capture.frame import Frame
from livebridge.capture.sources import Capabilities, ExposureSetting, SourceBase
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError

MONO_SOCKETS = ("CAM_B", "CAM_C")
DEFAULT_SIZE = (1280, 800)
ISO_RANGE = (100.0, 1600.0)
EXPOSURE_RANGE_US = (20.0, 33000.0)


def list_devices() -> list[dict]:
    """OAK devices visible now (USB and network): ``{"id", "name", "state", "platform", "protocol"}`` each."""
    out = []
    for info in dai.Device.getAllAvailableDevices():
        out.append({"id": info.getDeviceId(), "name": info.name, "state": str(info.state).split(".")[-1],
                    "platform": str(info.platform).split(".")[-1], "protocol": str(info.protocol).split(".")[-1]})
    return out


def _socket(name: str):
    try:
        return getattr(dai.CameraBoardSocket, name.upper())
    except AttributeError:
        known = [n for n in dir(dai.CameraBoardSocket) if n.startswith("CAM_")]
        raise InputError(f"unknown camera socket {name!r}; known: {', '.join(known)}", field="socket") from None


def _seconds(delta: datetime.timedelta) -> float:
    return delta.total_seconds()


def frame_from_message(message, source_id: str, sync_domain: str) -> Frame:
    """A livebridge :class:`Frame` from a DepthAI ``ImgFrame`` (grayscale, mid-exposure host time)."""
    if message.getType() in (dai.ImgFrame.Type.GRAY8, dai.ImgFrame.Type.RAW8):
        image = np.asarray(message.getFrame(), dtype=np.uint8).reshape(message.getHeight(), message.getWidth())
    else:
        image = message.getCvFrame()
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    exposure_us = _seconds(message.getExposureTime()) * 1e6
    iso = float(message.getSensitivity())
    t = _seconds(message.getTimestamp(dai.CameraExposureOffset.MIDDLE))
    return Frame(np.ascontiguousarray(image), t, message.getSequenceNum(), source_id,
                 exposure_us if exposure_us > 0 else math.nan, iso if iso > 0 else math.nan, sync_domain)


def calibration_from_handler(handler, sockets=MONO_SOCKETS, sizes=None, names=None) -> CameraGroup:
    """Cameras from a DepthAI ``CalibrationHandler`` (factory EEPROM calibration).

    Parameters
    ----------
    handler : depthai.CalibrationHandler
    sockets : sequence of str
        Board sockets; the first one's camera frame is the world frame.
    sizes : sequence of (width, height), optional
        Image size each camera delivers (intrinsics are scaled to it); default 1280x800.
    names : sequence of str, optional
        Camera names; default the socket names.

    Returns
    -------
    CameraGroup
        mm; distortion as OpenCV coefficients (8 when the rational terms are used, else 5; fisheye: 4).
    """
    sockets = [s.upper() for s in sockets]
    sizes = sizes or [DEFAULT_SIZE] * len(sockets)
    names = names or sockets
    reference = _socket(sockets[0])
    cameras = []
    for name, socket_name, (width, height) in zip(names, sockets, sizes):
        socket = _socket(socket_name)
        matrix = np.array(handler.getCameraIntrinsics(socket, width, height), dtype=np.float64)
        coefficients = np.array(handler.getDistortionCoefficients(socket), dtype=np.float64)
        fisheye = handler.getDistortionModel(socket) == dai.CameraModel.Fisheye
        if fisheye:
            distortions = coefficients[:4]
        elif coefficients.size >= 8 and np.any(coefficients[5:8] != 0):
            distortions = coefficients[:8]
        else:
            distortions = coefficients[:5]
        if socket == reference:
            world2cam = np.eye(4)
        else:
            world2cam = np.array(handler.getCameraExtrinsics(reference, socket, unit=dai.LengthUnit.MILLIMETER))
        rotation = cv2.Rodrigues(world2cam[:3, :3])[0].ravel()
        cameras.append(Camera(name, (width, height), matrix, distortions, rotation, world2cam[:3, 3], fisheye))
    return CameraGroup(cameras)


def export_calibration(path, device_id: str = "any", sockets=MONO_SOCKETS, size=DEFAULT_SIZE) -> CameraGroup:
    """Read a device's factory calibration and save it as a livebridge calibration file; returns the cameras."""
    info = _find_device(device_id)
    with dai.Device(info) as device:
        handler = device.readCalibration()
        names = [f"{info.getDeviceId()}/{s}" for s in sockets]
        group = calibration_from_handler(handler, sockets, [size] * len(sockets), names)
    from livebridge.calibration.calibfile import save_calibration

    save_calibration(path, group)
    return group


def _find_device(device_id: str):
    """The DeviceInfo of ``device_id`` (``any``: the first), found by a quick scan, without a long search."""
    available = dai.Device.getAllAvailableDevices()
    if not available:
        raise InputError("no DepthAI (OAK) device found", f"depthai://{device_id}")
    if device_id in ("", "any"):
        return available[0]
    for info in available:
        if device_id in (info.getDeviceId(), info.name):
            return info
    known = ", ".join(i.getDeviceId() for i in available)
    raise InputError(f"device not found; available: {known}", f"depthai://{device_id}")


class OakDevice:
    """One OAK device and its pipeline of grayscale cameras (see the module docstring).

    Parameters
    ----------
    device_id : str
        Device id (``1844301011B546F500``), IP/USB name, or ``any``.
    sockets : sequence of str
        Camera board sockets; default the two mono cameras.
    fps : float
    size : tuple of int
        Output ``(width, height)``.
    exposure_us, iso : float, optional
        Manual exposure; None: auto exposure.
    ir_flood, dot_projector : float
        IR flood light and dot projector intensity in [0, 1] where the device has them.
    queue_size : int
    """

    def __init__(self, device_id: str = "any", sockets=MONO_SOCKETS, fps: float = 60.0, size=DEFAULT_SIZE,
                 exposure_us: float | None = None, iso: float | None = None, ir_flood: float = 0.5,
                 dot_projector: float = 0.0, queue_size: int = 2):
        self.device_id, self.sockets = device_id, [s.upper() for s in sockets]
        for socket in self.sockets:
            _socket(socket)
        self.fps, self.size = float(fps), tuple(size)
        self.exposure_us, self.iso = exposure_us, iso
        self.ir_flood, self.dot_projector = float(ir_flood), float(dot_projector)
        self.queue_size = queue_size
        self.device = self.pipeline = None
        self._outputs: dict[str, object] = {}
        self._controls: dict[str, object] = {}
        self._users = 0
        self._lock = threading.Lock()
        self.sync_domain = f"oak:{device_id}"

    def sources(self) -> list[OakCameraSource]:
        return [OakCameraSource(self, socket) for socket in self.sockets]

    def acquire(self) -> None:
        with self._lock:
            if self._users == 0:
                self._start()
            self._users += 1

    def release(self) -> None:
        with self._lock:
            self._users = max(0, self._users - 1)
            if self._users == 0 and self.device is not None:
                try:
                    self.pipeline.stop()
                finally:
                    self.device.close()
                    self.device = self.pipeline = None

    def _start(self) -> None:
        info = _find_device(self.device_id)
        self.device_id = info.getDeviceId()
        self.sync_domain = f"oak:{self.device_id}"
        self.device = dai.Device(info)
        self.pipeline = dai.Pipeline(self.device)
        for socket_name in self.sockets:
            camera = self.pipeline.create(dai.node.Camera).build(_socket(socket_name), sensorFps=self.fps)
            if self.exposure_us is not None:
                camera.initialControl.setManualExposure(int(self.exposure_us), int(self.iso or 400))
            output = camera.requestOutput(self.size, type=dai.ImgFrame.Type.GRAY8, fps=self.fps)
            self._outputs[socket_name] = output.createOutputQueue(maxSize=self.queue_size, blocking=False)
            self._controls[socket_name] = camera.inputControl.createInputQueue()
        self.pipeline.start()
        if self.device.getIrDrivers():
            self.device.setIrFloodLightIntensity(self.ir_flood)
            self.device.setIrLaserDotProjectorIntensity(self.dot_projector)

    def calibration(self) -> CameraGroup:
        """The running device's factory calibration (world = first socket's camera, mm)."""
        if self.device is None:
            raise RuntimeError("device not started")
        names = [f"{self.device_id}/{s}" for s in self.sockets]
        return calibration_from_handler(self.device.readCalibration(), self.sockets, [self.size] * len(self.sockets),
                                        names)


class OakCameraSource(SourceBase):
    """One camera socket of an :class:`OakDevice` as a camera source; the device starts with its first source."""

    def __init__(self, device: OakDevice, socket: str):
        self.oak, self.socket = device, socket.upper()
        self.source_id = f"{device.device_id}/{self.socket}"
        self._started = False

    def start(self) -> None:
        self.oak.acquire()
        self._started = True
        self.source_id = f"{self.oak.device_id}/{self.socket}"
        self._ended, self._error = False, None

    def stop(self) -> None:
        if self._started:
            self._started = False
            self.oak.release()
        self._end(None)

    def read(self, timeout: float | None = None) -> Frame | None:
        if not self._started or self._ended:
            return None
        queue = self.oak._outputs[self.socket]
        try:
            message = queue.get(datetime.timedelta(seconds=timeout)) if timeout is not None else queue.get()
        except RuntimeError as error:  # queue closed: device gone
            self._end(f"{self.source_id}: device disconnected ({error})")
            return None
        if message is None:
            if self.oak.device is None or self.oak.device.isClosed():
                self._end(f"{self.source_id}: device disconnected")
            return None
        return frame_from_message(message, self.source_id, self.oak.sync_domain)

    def set_exposure(self, manual: bool, exposure_us: float | None = None, gain: float | None = None):
        """Send a ``CameraControl``; the values actually used arrive with the frames (``Frame.exposure_us``,
        ``Frame.gain`` = ISO) a few frames later. Returns the clamped request."""
        control = dai.CameraControl()
        if manual:
            exposure_us = float(np.clip(exposure_us or self.oak.exposure_us or 2000.0, *EXPOSURE_RANGE_US))
            gain = float(np.clip(gain or self.oak.iso or 400.0, *ISO_RANGE))
            control.setManualExposure(int(exposure_us), int(gain))
        else:
            control.setAutoExposureEnable()
            exposure_us = gain = math.nan
        self.oak._controls[self.socket].send(control)
        return ExposureSetting(manual, exposure_us, gain)

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(size=self.oak.size, fps=self.oak.fps, manual_exposure=True,
                            exposure_range_us=EXPOSURE_RANGE_US, gain_range=ISO_RANGE,
                            hardware_sync=len(self.oak.sockets) > 1, formats=("GRAY8",))


_URL_KEYS = {"fps", "width", "height", "exposure_us", "iso", "ir", "dots", "queue"}


def open_url(url: DeviceURL) -> list[OakCameraSource]:
    """``depthai://DEVICE_ID/CAM_B?fps=60&width=1280&height=800&exposure_us=2000&iso=400&ir=0.5&dots=0``.

    Without a socket (``depthai://DEVICE_ID``) both mono cameras are opened as a hardware-synced pair.
    Nothing touches the device until a source starts.
    """
    url.check_known(_URL_KEYS)
    os.environ.setdefault("DEPTHAI_SEARCH_TIMEOUT", "1500")  # ms; we scan first and fail fast anyway
    sockets = [s for s in url.path.strip("/").split(",") if s] or list(MONO_SOCKETS)
    size = (url.take("width", int, DEFAULT_SIZE[0]), url.take("height", int, DEFAULT_SIZE[1]))
    device = OakDevice(url.netloc or "any", sockets, url.take("fps", float, 60.0), size,
                       url.take("exposure_us", float), url.take("iso", float), url.take("ir", float, 0.5),
                       url.take("dots", float, 0.0), url.take("queue", int, 2))
    return device.sources()

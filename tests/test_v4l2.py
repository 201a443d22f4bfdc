"""V4L2 driver: configuration order and read-back, exposure units, grayscale conversion, grab thread and
unplug, against a fake capture object and OpenCV's image-sequence backend."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from livebridge.capture.sources import CameraSource
from livebridge.devices.registry import open_camera
from livebridge.drivers.v4l2 import (
    V4L2Source,
    fourcc_code,
    fourcc_text,
    list_devices,
    to_gray,
)
from livebridge.errors import InputError


class FakeCapture:
    """A V4L2 camera as OpenCV's VideoCapture shows it: snaps requests to its modes, raw MJPG buffers."""

    MODES = {"MJPG": [(1280, 720, 60.0), (640, 480, 120.0)], "YUYV": [(640, 480, 30.0), (320, 240, 60.0)]}

    def __init__(self, unplug_after=None, rng=None):
        self.calls = []
        self.fourcc, (self.width, self.height, self.fps) = "YUYV", self.MODES["YUYV"][0]
        self.props = {cv2.CAP_PROP_AUTO_EXPOSURE: 3, cv2.CAP_PROP_EXPOSURE: 156, cv2.CAP_PROP_GAIN: 0,
                      cv2.CAP_PROP_CONVERT_RGB: 1, cv2.CAP_PROP_BUFFERSIZE: 4}
        self.unplug_after = unplug_after
        self.grabbed = 0
        self.released = False
        self.rng = rng or np.random.default_rng(0)
        self.last = None

    def isOpened(self):
        return not self.released

    def set(self, prop, value):
        self.calls.append(prop)
        if prop == cv2.CAP_PROP_FOURCC:
            text = fourcc_text(value)
            if text in self.MODES:
                self.fourcc = text
                self.width, self.height, self.fps = self.MODES[text][0]
        elif prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            want = (value, self.height) if prop == cv2.CAP_PROP_FRAME_WIDTH else (self.width, value)
            best = min(self.MODES[self.fourcc], key=lambda m: abs(m[0] - want[0]) + abs(m[1] - want[1]))
            self.width, self.height, self.fps = best
        elif prop == cv2.CAP_PROP_FPS:
            self.fps = min(value, [m for m in self.MODES[self.fourcc] if m[:2] == (self.width, self.height)][0][2])
        elif prop == cv2.CAP_PROP_EXPOSURE:
            self.props[prop] = int(np.clip(value, 1, 5000))
        elif prop == cv2.CAP_PROP_BUFFERSIZE:
            self.props[prop] = int(np.clip(value, 1, 4))
        else:
            self.props[prop] = value
        return True

    def get(self, prop):
        if prop == cv2.CAP_PROP_FOURCC:
            return float(fourcc_code(self.fourcc))
        if prop == cv2.CAP_PROP_FRAME_WIDTH:
            return float(self.width)
        if prop == cv2.CAP_PROP_FRAME_HEIGHT:
            return float(self.height)
        if prop == cv2.CAP_PROP_FPS:
            return float(self.fps)
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.kernel_ms
        return float(self.props.get(prop, -1))

    def grab(self):
        if self.unplug_after is not None and self.grabbed >= self.unplug_after:
            time.sleep(0.002)
            return False
        time.sleep(1.0 / self.fps)
        self.kernel_ms = time.monotonic() * 1000.0 - 1.0
        self.grabbed += 1
        image = np.full((self.height, self.width), 10, np.uint8)
        cv2.circle(image, (100 + self.grabbed % 50, 100), 6, 250, -1)
        self.last = image
        return True

    def retrieve(self):
        if self.props[cv2.CAP_PROP_CONVERT_RGB]:
            return True, cv2.cvtColor(self.last, cv2.COLOR_GRAY2BGR)
        if self.fourcc == "MJPG":
            ok, data = cv2.imencode(".jpg", self.last, [cv2.IMWRITE_JPEG_QUALITY, 95])
            return ok, data.reshape(1, -1)
        yuyv = np.empty((self.height, self.width * 2), np.uint8)
        yuyv[:, 0::2], yuyv[:, 1::2] = self.last, 128
        return True, yuyv.reshape(1, -1)

    def release(self):
        self.released = True


def test_configuration_order_and_read_back():
    fake = FakeCapture()
    source = V4L2Source("/dev/fake0", 1200, 700, 90, "MJPG", exposure_us=2000, gain=3, buffer_size=1,
                        capture_factory=lambda device: fake)
    assert isinstance(source, CameraSource)
    with source:
        order = [p for p in fake.calls if p in (cv2.CAP_PROP_FOURCC, cv2.CAP_PROP_FRAME_WIDTH,
                                                 cv2.CAP_PROP_FRAME_HEIGHT, cv2.CAP_PROP_FPS)]
        assert order == [cv2.CAP_PROP_FOURCC, cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT, cv2.CAP_PROP_FPS]
        assert source.fourcc == "MJPG" and source.size == (1280, 720) and source.fps == 60.0  # what it accepted
        assert fake.props[cv2.CAP_PROP_BUFFERSIZE] == 1 and fake.props[cv2.CAP_PROP_CONVERT_RGB] == 0
        assert fake.props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1 and fake.props[cv2.CAP_PROP_EXPOSURE] == 20  # 100 us units
        assert source.exposure.manual and source.exposure.exposure_us == 2000 and source.exposure.gain == 3
        frames = [source.read(timeout=1.0) for _ in range(4)]
        applied = source.set_exposure(True, 1e9)
        assert applied.exposure_us == 5000 * 100  # clamped by the camera, read back
        assert not source.set_exposure(False).manual and fake.props[cv2.CAP_PROP_AUTO_EXPOSURE] == 3
    assert fake.released and source.ended and source.error is None
    for frame in frames:
        assert frame.image.shape == (720, 1280) and frame.image.dtype == np.uint8
        assert frame.image.max() > 200 and frame.image[0, 0] < 20  # MJPG decoded to grayscale
        assert source.timestamp_source == "kernel"
        assert time.monotonic() - 2 < frame.t_capture < time.monotonic()
    assert [f.seq for f in frames] == sorted({f.seq for f in frames})
    assert all(b.t_capture > a.t_capture for a, b in zip(frames, frames[1:]))


def test_yuyv_and_unplug_end_the_source_cleanly(tmp_path):
    node = tmp_path / "video7"  # stands for the device node; the fake "unplugs" by removing it
    node.write_bytes(b"")

    class Unplugging(FakeCapture):
        def grab(self):
            if self.grabbed >= 6 and node.exists():
                node.unlink()
            return super().grab()

    fake = Unplugging(unplug_after=6)
    source = V4L2Source(str(node), 640, 480, 30, "YUYV", capture_factory=lambda device: fake)
    got = []
    with source:
        while (frame := source.read(timeout=2.0)) is not None:
            got.append(frame)
        assert source.ended and "unplugged" in source.error
    assert 1 <= len(got) <= 6 and got[-1].image.shape == (480, 640)
    assert np.array_equal(got[-1].image, fake.last)  # Y bytes of YUYV, exactly
    assert fake.released
    # a camera that fails to grab while its node stays is reported too
    fake = FakeCapture(unplug_after=2)
    source = V4L2Source("/dev/fake1", 640, 480, 30, "YUYV", capture_factory=lambda device: fake)
    with source:
        while source.read(timeout=2.0) is not None:
            pass
    assert "stopped delivering" in source.error


def test_to_gray_formats(rng):
    image = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    assert to_gray(image, "GREY", (64, 48)) is image
    np.testing.assert_array_equal(to_gray(image.reshape(1, -1), "GREY", (64, 48)), image)
    y16 = (image.astype(np.uint16) << 8) | 0x3F
    np.testing.assert_array_equal(to_gray(y16.view(np.uint8).reshape(1, -1), "Y16", (64, 48)), image)
    uyvy = np.empty((48, 128), np.uint8)
    uyvy[:, 1::2], uyvy[:, 0::2] = image, 128
    np.testing.assert_array_equal(to_gray(uyvy.reshape(-1), "UYVY", (64, 48)), image)
    assert to_gray(np.zeros((1, 100), np.uint8), "MJPG", (64, 48)) is None  # corrupt JPEG
    bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    np.testing.assert_array_equal(to_gray(bgr, "MJPG", (64, 48)), image)


def test_opencv_image_sequence_backend(tmp_path, rng):
    images = [rng.integers(0, 256, (40, 60), dtype=np.uint8) for _ in range(5)]
    for k, image in enumerate(images):
        cv2.imwrite(str(tmp_path / f"f{k:03d}.png"), image)
    pattern = str(tmp_path / "f%03d.png")
    source = V4L2Source(pattern, 60, 40, 30, "GREY", source_id="seq",
                        capture_factory=lambda device: cv2.VideoCapture(device, cv2.CAP_IMAGES))
    got = []
    with source:
        while (frame := source.read(timeout=2.0)) is not None and len(got) < 10:
            got.append(frame)
    assert source.ended and "stopped delivering" in source.error  # end of the sequence, reported
    assert source.size == (60, 40) and source.timestamp_source == "host"
    assert len(got) >= 2 and all(f.source_id == "seq" for f in got)
    for frame in got:  # the newest frames are kept; each equals one of the files
        assert any(np.array_equal(frame.image, image) for image in images)


def test_url_errors():
    with pytest.raises(InputError, match="exposure"):
        open_camera("v4l2:///dev/video0?exposure_us=fast")
    with pytest.raises(InputError, match="unknown parameter"):
        open_camera("v4l2:///dev/video0?colour=1")
    with pytest.raises(InputError, match="buffer"):
        open_camera("v4l2:///dev/video0?buffer=4")
    source = open_camera("v4l2:///dev/does-not-exist?width=640&fourcc=yuyv&name=left")
    assert source.source_id == "left" and source.requested["fourcc"] == "YUYV"
    with pytest.raises(InputError, match="does-not-exist"):
        source.start()


def test_list_devices_without_cameras(tmp_path):
    assert list_devices(str(tmp_path)) == []


@pytest.mark.hardware
def test_real_camera_delivers_frames():
    devices = list_devices()
    if not devices:
        pytest.skip("no V4L2 camera")
    source = V4L2Source(devices[0].path, 640, 480, 30)
    with source:
        frame = source.read(timeout=5.0)
    assert frame is not None and frame.image.ndim == 2

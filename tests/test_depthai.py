"""DepthAI driver, host only: ImgFrame conversion, factory-calibration conversion, device search failing fast.
Real devices: ``hardware`` tests, skipped when none is connected."""

from __future__ import annotations

import datetime
import time

import cv2
import numpy as np
import pytest

dai = pytest.importorskip("depthai")

from livebridge.capture.sources import CameraSource  # noqa: E402
from livebridge.devices.registry import open_cameras  # noqa: E402
from livebridge.drivers import depthai as oak  # noqa: E402
from livebridge.errors import InputError  # noqa: E402


def test_host_only_pipeline_is_available():
    pipeline = dai.Pipeline(createImplicitDevice=False)
    assert pipeline is not None
    with pytest.raises(RuntimeError):  # device nodes need a device: the driver only builds them on start
        pipeline.create(dai.node.Camera)


def test_frame_from_imgframe(rng):
    image = rng.integers(0, 256, (8, 12), dtype=np.uint8)
    message = dai.ImgFrame()
    message.setType(dai.ImgFrame.Type.GRAY8)
    message.setWidth(12)
    message.setHeight(8)
    message.setData(image.ravel())
    message.setSequenceNum(41)
    message.setTimestamp(datetime.timedelta(seconds=1234.5))
    frame = oak.frame_from_message(message, "X/CAM_B", "oak:X")
    np.testing.assert_array_equal(frame.image, image)
    assert frame.seq == 41 and frame.source_id == "X/CAM_B" and frame.sync_domain == "oak:X"
    assert frame.t_capture == pytest.approx(1234.5)
    assert np.isnan(frame.exposure_us) and np.isnan(frame.gain)  # unknown on a bare message


def test_factory_calibration_to_camera_group():
    handler = dai.CalibrationHandler()
    K = [[800.0, 0, 640.0], [0, 801.0, 400.0], [0, 0, 1]]
    for socket in (dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C):
        handler.setCameraIntrinsics(socket, K, dai.Size2f(1280, 800))
        handler.setDistortionCoefficients(socket, [0.01, -0.02, 0.001, 0.0005, 0.003] + [0.0] * 9)
    rotation = cv2.Rodrigues(np.array([0.0, 0.02, 0.0]))[0]
    handler.setCameraExtrinsics(dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C, rotation.tolist(),
                                [-7.5, 0.0, 0.0])  # cm: a 75 mm baseline
    group = oak.calibration_from_handler(handler, ("CAM_B", "CAM_C"), [(1280, 800), (640, 400)])
    left, right = group.cameras
    np.testing.assert_allclose(left.matrix, K)
    np.testing.assert_allclose(right.matrix[:2], np.array(K)[:2] / 2, atol=1.0)  # scaled to the output size
    np.testing.assert_allclose(right.translation, [-75.0, 0, 0], atol=1e-6)  # mm
    np.testing.assert_allclose(cv2.Rodrigues(right.rotation)[0], rotation, atol=1e-6)
    np.testing.assert_allclose(left.distortions, [0.01, -0.02, 0.001, 0.0005, 0.003])
    assert np.linalg.norm(right.center - left.center) == pytest.approx(75.0)
    # a point 600 mm in front of the left camera projects near both image centres
    pixels = group.project(np.array([[37.5, 0.0, 600.0]]))[:, 0]
    assert np.all(np.abs(pixels[0] - [640 + 800 * 37.5 / 600, 400]) < 5)


def test_no_device_fails_fast_and_clearly():
    sources = open_cameras("depthai://any?fps=30&exposure_us=2000&iso=400")
    assert [s.socket for s in sources] == ["CAM_B", "CAM_C"] and all(isinstance(s, CameraSource) for s in sources)
    assert sources[0].capabilities.hardware_sync
    if oak.list_devices():
        pytest.skip("a device is connected")
    start = time.monotonic()
    with pytest.raises(InputError, match="no DepthAI"):
        sources[0].start()
    assert time.monotonic() - start < 5.0
    with pytest.raises(InputError, match="socket"):
        open_cameras("depthai://any/CAM_Z")
    with pytest.raises(InputError, match="unknown parameter"):
        open_cameras("depthai://any?gain=2")


@pytest.mark.hardware
def test_oak_mono_pair_delivers_synced_frames():
    if not oak.list_devices():
        pytest.skip("no DepthAI device")
    sources = open_cameras("depthai://any?fps=30&exposure_us=2000&iso=400")
    for source in sources:
        source.start()
    try:
        left, right = sources[0].read(timeout=5.0), sources[1].read(timeout=5.0)
        assert left is not None and right is not None and left.sync_domain == right.sync_domain
        assert abs(left.t_capture - time.monotonic()) < 1.0
        group = sources[0].oak.calibration()
        assert len(group) == 2
    finally:
        for source in sources:
            source.stop()

"""Multi-camera calibration: boards, intrinsics, extrinsics, bundle adjustment (livebridge.calibration)."""

"""Simulated camera rig: frame sets per second (4 x 1280x800, one core) vs naive OpenCV drawing; centroid accuracy."""

from __future__ import annotations

import time

import numpy as np

FRAMESETS_REQUIRED = 30.0
CENTROID_RMS_REQUIRED_PX = 0.1


def _naive_render(rig, seq: int, rng: np.random.Generator) -> list[np.ndarray]:
    """The peer: every camera drawn from scratch with OpenCV's anti-aliased circles and full-frame noise."""
    import cv2

    truth = rig.truth(seq)
    images = []
    for c, camera in enumerate(rig.cameras.cameras):
        width, height = camera.size
        image = rig._background(c, 1.0).astype(np.int16)
        canvas = np.zeros((height, width), np.uint8)
        for (x, y), r in zip(truth.points_2d[c][truth.visible[c]], truth.radius_px[c][truth.visible[c]]):
            cv2.circle(canvas, (int(round(x * 16)), int(round(y * 16))), int(round(r * 16)), 230, -1, cv2.LINE_AA, 4)
        image = np.maximum(image, canvas) + rng.normal(0, rig.config.noise_sigma, (height, width)).astype(np.int16)
        images.append(np.clip(image, 0, 255).astype(np.uint8))
    return images


def centroids_opencv(image: np.ndarray, threshold: float = 60.0) -> np.ndarray:
    """Intensity-weighted centroids of bright blobs (OpenCV connected components + moments), shape (n, 2)."""
    import cv2

    mask = (image > threshold).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    out = []
    for k in range(1, count):
        x, y, w, h, area = stats[k]
        if area < 3:
            continue
        x0, y0 = max(x - 2, 0), max(y - 2, 0)
        patch = image[y0:y + h + 2, x0:x + w + 2].astype(np.float32)
        border = np.concatenate([patch[0], patch[-1], patch[:, 0], patch[:, -1]])
        weights = np.clip(patch - np.median(border), 0, None)
        moments = cv2.moments(weights)
        if moments["m00"] > 0:
            out.append((x0 + moments["m10"] / moments["m00"], y0 + moments["m01"] / moments["m00"]))
    return np.array(out).reshape(-1, 2)


def _detector():
    """The production detector when it has landed (``livebridge.reconstruct.detect.detect_blobs``), else the
    OpenCV centroid."""
    try:
        from livebridge.reconstruct.detect import detect_blobs
    except ImportError:
        return "opencv-moments", centroids_opencv
    return "livebridge.reconstruct.detect.detect_blobs", detect_blobs


def _match(found: np.ndarray, truth: np.ndarray, radius: float = 2.0) -> np.ndarray:
    """Error vectors of true points matched to a detection within ``radius`` pixels, shape (n_matched, 2)."""
    if len(found) == 0 or len(truth) == 0:
        return np.zeros((0, 2))
    distance = np.linalg.norm(truth[:, None] - found[None], axis=-1)
    nearest = distance.argmin(axis=1)
    ok = distance[np.arange(len(truth)), nearest] < radius
    return found[nearest[ok]] - truth[ok]


def run(quick: bool, log) -> dict:
    import cv2

    from livebridge.simulators.rig import RigConfig, SimRig, default_face

    basis, markers = default_face()
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        rig = SimRig(basis, markers, n_cameras=4, config=RigConfig(size=(1280, 800), noise_sigma=2.0), seed=1)
        rig.start()
        n = 30 if quick else 300
        next(rig.framesets(1))  # warm-up
        start = time.perf_counter()
        for _ in rig.framesets(n, start=1):
            pass
        ours = n / (time.perf_counter() - start)  # SimRig.render's cost: framesets() only wraps its frames
        log(f"sim rig: {ours:.1f} frame sets/s, {1000 / ours:.2f} ms per frame set "
            f"(4 x 1280x800, {len(markers)} markers, one thread)")

        rng = np.random.default_rng(0)
        n_naive = 10 if quick else 60
        start = time.perf_counter()
        for seq in range(1, n_naive + 1):
            _naive_render(rig, seq, rng)
        naive = n_naive / (time.perf_counter() - start)
        log(f"naive OpenCV drawing + full-frame noise: {naive:.1f} frame sets/s")

        # centroid accuracy at zero noise
        clean = SimRig(basis, markers, n_cameras=4, config=RigConfig(noise_sigma=0.0), seed=1)
        name, detect = _detector()
        errors, n_true = [], 0
        for frameset in clean.framesets(3 if quick else 20, start=10):
            truth = frameset.truth
            for c, frame in enumerate(frameset.frames):
                pts = truth.points_2d[c][truth.visible[c]]
                gap = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(len(pts)) * 1e9
                alone = pts[gap.min(axis=1) > 12]  # discs that do not touch another
                n_true += len(alone)
                errors.append(_match(detect(frame.image), alone))
        errors = np.concatenate(errors)
        rms = float(np.sqrt((errors ** 2).sum(axis=1).mean()))
        log(f"centroid RMS at zero noise ({name}): {rms:.4f} px over {len(errors)}/{n_true} markers")
    finally:
        cv2.setNumThreads(threads)
    return {
        "framesets_per_s": round(ours, 2),
        "ms_per_frameset": round(1000 / ours, 3),
        "naive_opencv_framesets_per_s": round(naive, 2),
        "speedup_vs_naive": round(ours / naive, 2),
        "cameras": 4,
        "size": [1280, 800],
        "markers": len(markers),
        "centroid_rms_px": round(rms, 4),
        "centroid_detector": name,
        "centroid_detected_fraction": round(len(errors) / max(n_true, 1), 4),
        "framesets_required": FRAMESETS_REQUIRED,
        "centroid_rms_required_px": CENTROID_RMS_REQUIRED_PX,
        "pass": bool(ours > FRAMESETS_REQUIRED and rms < CENTROID_RMS_REQUIRED_PX),
        "quick": quick,
    }

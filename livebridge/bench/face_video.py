"""Face-video simulator: frames per second (one core) vs an OpenCV painter's-algorithm renderer; LED accuracy.

The simulator (compiled z-buffer, per-pixel smooth shading and texture, LEDs, noise) is timed on a take
with head motion and light drift at 360x240 (the CoArt paper's size) and larger sizes; the peer draws
the same deformed, posed mesh flat-shaded with ``cv2.fillConvexPoly`` per triangle, far to near (the
marker rig's background renderer, per frame), without texture. Times are CPU seconds of this thread
(``time.thread_time``), so a busy machine does not make the figure wrong; wall-clock frames per second are
reported beside them. Accuracy: the blob detector's LED centroids against the simulator's true LED pixels.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

SIZES = ((360, 240), (640, 400), (1280, 800))
SIMULATOR_FPS_REQUIRED = 100.0  # at 360x240 on one core
LED_ERROR_REQUIRED_PX = 0.5  # largest detected-vs-true LED offset


def _video(size: tuple[int, int], seed: int = 1):
    from livebridge.face.builtin import builtin_basis
    from livebridge.simulators.face_video import FaceVideo, FaceVideoConfig

    config = FaceVideoConfig(width=size[0], height=size[1], seed=seed, head_turn_deg=10.0, light_drift=0.2,
                             script="everyday")
    return FaceVideo(builtin_basis(), config)


def _timed(render: Callable[[int], object], n_frames: int) -> tuple[float, float]:
    """(CPU frames per second of this thread, wall-clock frames per second) of ``render(seq)``."""
    render(0)  # compiled kernels loaded, caches warm
    cpu, wall = time.thread_time(), time.perf_counter()
    for seq in range(1, n_frames + 1):
        render(seq)
    return n_frames / max(time.thread_time() - cpu, 1e-9), n_frames / max(time.perf_counter() - wall, 1e-9)


def simulator_frames_per_s(size: tuple[int, int] = (360, 240), n_frames: int = 200) -> float:
    """Frames per CPU second (one core) of the face-video simulator at ``size``, head moving, light drifting."""
    video = _video(size)
    return _timed(video.frame, n_frames)[0]


def painter_render(video, seq: int, rng: np.random.Generator) -> np.ndarray:
    """The peer: the frame's deformed, posed mesh, flat Lambert shading per triangle, drawn far to near with
    ``cv2.fillConvexPoly``, plus Gaussian noise; uint8 (height, width)."""
    import cv2

    from livebridge.face.meshio import triangle_normals

    basis, config = video.basis, video.config
    t = seq / config.fps
    pose = video.head_pose_at(t)
    light = video.light_at(t)
    model = basis.neutral + np.tensordot(video.contractions_at(t), basis.elements, axes=1)
    world = model @ pose[:3, :3].T + pose[:3, 3]
    camera = video.camera()
    pixels = camera.project(world)
    depth = (world @ camera.world2cam[:3, :3].T + camera.world2cam[:3, 3])[:, 2]
    normals = triangle_normals(world, basis.triangles)
    shade = config.skin_level * 0.72 * (config.ambient + light.intensity * np.clip(normals @ light.direction, 0, None))
    order = np.argsort(-depth[basis.triangles].mean(axis=1))
    image = np.full((config.height, config.width), config.background_level, np.float32)
    fixed = np.rint(pixels * 16).astype(np.int32)
    for tri in order:
        cv2.fillConvexPoly(image, fixed[basis.triangles[tri]], float(shade[tri]), lineType=cv2.LINE_8, shift=4)
    image += rng.normal(0.0, config.noise, image.shape).astype(np.float32)
    return np.clip(image + 0.5, 0, 255).astype(np.uint8)


def led_errors(video, n_frames: int) -> np.ndarray:
    """Distance (px) from each shown LED's true pixel to the nearest detected blob, over ``n_frames`` frames
    spread through the take; shape (n_shown,)."""
    from livebridge.reconstruct.detect import DetectConfig, detect_blobs

    config = DetectConfig(threshold=235.0, max_area=2000)
    errors = []
    for seq in np.linspace(0, 60 * video.config.fps, n_frames).astype(int):
        frame = video.frame(int(seq))
        shown = frame.led_points_2d[np.isfinite(frame.led_points_2d).all(axis=1)]
        blobs = detect_blobs(frame.image, config)
        if len(shown) == 0:
            continue
        if len(blobs) == 0:
            errors.extend([np.inf] * len(shown))
            continue
        errors.extend(np.linalg.norm(shown[:, None] - blobs[None], axis=2).min(axis=1))
    return np.asarray(errors)


def run(quick: bool = False, log: Callable[[str], None] = print) -> dict:
    n_frames = 40 if quick else 200
    result: dict = {}
    video = _video(SIZES[0])
    cpu_fps, wall_fps = _timed(video.frame, n_frames)
    rng = np.random.default_rng(0)
    peer_cpu, _ = _timed(lambda seq: painter_render(video, seq, rng), max(10, n_frames // 4))
    result.update(simulator_frames_per_s=cpu_fps, simulator_wall_frames_per_s=wall_fps,
                  painter_frames_per_s=peer_cpu, speedup_vs_painter=cpu_fps / peer_cpu)
    log(f"360x240: {cpu_fps:.0f} frames/s per core ({wall_fps:.0f} wall), OpenCV painter {peer_cpu:.0f} "
        f"-> x{cpu_fps / peer_cpu:.1f}")
    for size in SIZES[1:] if not quick else ():
        fps, _ = _timed(_video(size).frame, max(10, n_frames // 4))
        result[f"simulator_frames_per_s_{size[0]}x{size[1]}"] = fps
        log(f"{size[0]}x{size[1]}: {fps:.0f} frames/s per core")
    errors = led_errors(video, 10 if quick else 60)
    result.update(led_error_mean_px=float(np.mean(errors)), led_error_max_px=float(np.max(errors)),
                  leds_checked=int(len(errors)))
    log(f"LED centroids vs truth: mean {result['led_error_mean_px']:.3f} px, max {result['led_error_max_px']:.3f} px "
        f"({len(errors)} LEDs)")
    result.update(simulator_frames_per_s_required=SIMULATOR_FPS_REQUIRED, led_error_required_px=LED_ERROR_REQUIRED_PX)
    result["passed"] = bool(cpu_fps >= SIMULATOR_FPS_REQUIRED and result["led_error_max_px"] <= LED_ERROR_REQUIRED_PX)
    return result

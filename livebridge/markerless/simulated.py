"""Markerless takes from the face-video simulator: training, held-out takes, scoring (demo, bench, tests).

Every take films the same performer (skin seed 0, :data:`PERFORMER`); a held-out take differs by its
``seed`` (expressions, head motion, light drift, noise).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from livebridge.markerless.normalise import HeadRig, Normalisation
from livebridge.markerless.train import TrainConfig, TrainResult, combination_prompts, isolated_prompts, train

PERFORMER = 0  # the skin seed of every simulated take here


def face_video(basis, **config):
    """A :class:`~livebridge.simulators.face_video.FaceVideo` of ``basis`` filming :data:`PERFORMER`."""
    from livebridge.simulators.face_video import FaceVideo, FaceVideoConfig

    return FaceVideo(basis, FaceVideoConfig(skin_seed=PERFORMER, **config))


def training_prompts(video) -> tuple:
    """The gesture list of a simulated ``gestures`` take: every muscle, then the combined gestures."""
    from livebridge.simulators.performer import COMBINED_GESTURES

    names = video.script.gesture_names
    combined = {name: levels for name, levels in COMBINED_GESTURES.items() if name in names}
    return isolated_prompts(video.basis.names) + combination_prompts(combined)


def simulated_normalisation(video, head_rig: bool = True, **options) -> Normalisation:
    """How the simulated camera's images are normalised (its intrinsics; the rig's LEDs, or a fixed crop)."""
    camera = video.camera()
    rig = HeadRig.from_leds(video.head_rig_geometry()) if head_rig else None
    return Normalisation(camera.size, rig, camera.matrix, camera.distortions, **options)


def train_on_simulator(basis, fps: float = 30.0, seed: int = 0, config: TrainConfig | None = None,
                       images=None, use_mesh: bool = True, **options) -> tuple[TrainResult, object]:
    """Render a ``gestures`` training take (or use ``images``) and train on it; returns (result, video)."""
    video = face_video(basis, script="gestures", fps=fps, seed=seed)
    if images is None:
        images = training_images(video)
    mesh = (basis.neutral, basis.triangles) if use_mesh else None
    result = train(images, simulated_normalisation(video, **options), training_prompts(video), basis.names,
                   config or TrainConfig(),
                   mesh)
    return result, video


def training_images(video) -> np.ndarray:
    """Every frame of the video's (gestures) take, shape (n, H, W) uint8."""
    n_frames = int(round(video.script.duration * video.config.fps))
    return np.array([video.frame(i).image for i in range(n_frames)])


@dataclass
class MarkerlessScore:
    """Contraction error of solved frames against a face-video source's ground truth (thread-safe)."""

    source: object
    absolute: float = 0.0
    count: int = 0
    frames: int = 0
    worst_abs: float = 0.0

    def __post_init__(self):
        self._lock = threading.Lock()

    def __call__(self, frame) -> None:
        truth = self.source.truth(frame.seq).contractions
        error = np.abs(np.asarray(frame.contractions) - truth)
        with self._lock:
            self.frames += 1
            self.absolute += float(error.sum())
            self.count += error.size
            self.worst_abs = max(self.worst_abs, float(error.max()))

    @property
    def mae(self) -> float:
        return self.absolute / self.count if self.count else float("nan")

    def describe(self) -> str:
        """The summary line of a run."""
        return (f"contraction MAE vs ground truth: {self.mae:.4f} over {self.frames} frames "
                f"(worst {self.worst_abs:.3f})")

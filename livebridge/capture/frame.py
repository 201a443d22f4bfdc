"""Per-frame payloads of the capture stage: one camera image, and a synchronised set of them.

Times are seconds on the host's monotonic clock (``time.monotonic``) at mid-exposure where the source
knows it; every source maps its own clock (kernel buffer time, device clock) onto that one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True, eq=False)
class Frame:
    """One grayscale image from one camera.

    Attributes
    ----------
    image : ndarray of uint8, shape (height, width)
        Grayscale pixels; read-only.
    t_capture : float
        Host monotonic seconds at mid-exposure (or the best estimate the source has).
    seq : int
        Frame counter of the source; cameras in one hardware ``sync_domain`` share it for simultaneous frames.
    source_id : str
        The camera's name, unique in a rig (e.g. ``cam0``, ``/dev/video0``, ``1844301011B546F500/CAM_B``).
    exposure_us : float
        Exposure time in microseconds (NaN when unknown).
    gain : float
        Analogue gain or ISO as the source reports it (NaN when unknown).
    sync_domain : str
        Cameras triggered by one hardware clock share a domain; a free-running camera has its own.
    centroids : ndarray, shape (n_blobs, 2), or None
        Marker centroids already detected where the frame was taken (a camera node), distorted pixels,
        read-only; None: the host detects them in ``image``. A frame that carries centroids may carry no
        pixels (``image`` of shape (0, 0)) or a thumbnail.
    board_corners : ndarray, shape (n_corners, 2), or None
        A calibration board's corners already detected where the frame was taken (a camera node asked for
        the board), distorted pixels, NaN rows for corners not found, read-only; None: the host detects the
        board in ``image``.
    """

    image: np.ndarray
    t_capture: float
    seq: int
    source_id: str
    exposure_us: float = float("nan")
    gain: float = float("nan")
    sync_domain: str = ""
    centroids: np.ndarray | None = None
    board_corners: np.ndarray | None = None

    def __post_init__(self):
        image = np.asarray(self.image)
        if image.dtype != np.uint8 or image.ndim != 2:
            raise ValueError(f"Frame.image must be uint8 (height, width), got {image.dtype} {image.shape}")
        if image.flags.writeable:
            if image.base is not None or not image.flags.owndata:
                image = image.copy()
            image.setflags(write=False)
        object.__setattr__(self, "image", image)
        object.__setattr__(self, "t_capture", float(self.t_capture))
        object.__setattr__(self, "seq", int(self.seq))
        if not self.sync_domain:
            object.__setattr__(self, "sync_domain", self.source_id)
        if self.centroids is not None:
            centroids = np.array(self.centroids, dtype=np.float64).reshape(-1, 2)
            centroids.setflags(write=False)
            object.__setattr__(self, "centroids", centroids)
        if self.board_corners is not None:
            corners = np.array(self.board_corners, dtype=np.float64).reshape(-1, 2)
            corners.setflags(write=False)
            object.__setattr__(self, "board_corners", corners)

    @property
    def size(self) -> tuple[int, int]:
        """Image ``(width, height)`` in pixels."""
        return self.image.shape[1], self.image.shape[0]


@dataclass(frozen=True, eq=False)
class FrameSet:
    """Frames of every camera of a rig taken at (nearly) the same instant.

    Attributes
    ----------
    frames : tuple of (Frame or None), length n_cams
        In the rig's fixed camera order (``source_ids``); None where a camera delivered nothing.
    source_ids : tuple of str, length n_cams
    index : int
        Running number of the frame set from 0.
    t : float
        Host monotonic seconds: mean ``t_capture`` of the frames present (NaN when none is).
    skew : float
        Largest minus smallest ``t_capture`` of the frames present, seconds (0 with fewer than two).
    truth : object, optional
        Ground truth when a simulator made the frames (see :class:`livebridge.simulators.rig.SimTruth`).
    """

    frames: tuple[Frame | None, ...]
    source_ids: tuple[str, ...]
    index: int = 0
    t: float = float("nan")
    skew: float = 0.0
    truth: Any = None

    def __post_init__(self):
        object.__setattr__(self, "frames", tuple(self.frames))
        object.__setattr__(self, "source_ids", tuple(self.source_ids))
        if len(self.frames) != len(self.source_ids):
            raise ValueError(f"{len(self.frames)} frames for {len(self.source_ids)} cameras")

    @classmethod
    def from_frames(cls, frames, source_ids, index: int = 0, truth: Any = None) -> FrameSet:
        """Build a frame set and compute ``t`` and ``skew`` from the frames present."""
        times = [f.t_capture for f in frames if f is not None]
        t = float(np.mean(times)) if times else float("nan")
        skew = float(max(times) - min(times)) if len(times) > 1 else 0.0
        return cls(tuple(frames), tuple(source_ids), index, t, skew, truth)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, key: int | str) -> Frame | None:
        if isinstance(key, str):
            return self.frames[self.source_ids.index(key)]
        return self.frames[key]

    @property
    def present(self) -> np.ndarray:
        """Boolean mask, shape (n_cams,), of the cameras that delivered a frame."""
        return np.array([f is not None for f in self.frames])

    @property
    def complete(self) -> bool:
        """True when every camera delivered a frame."""
        return all(f is not None for f in self.frames)

    @property
    def images(self) -> list[np.ndarray | None]:
        """The images in camera order, None where missing."""
        return [None if f is None else f.image for f in self.frames]

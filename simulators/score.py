"""Scoring a pipeline's solved frames against the ground truth of the simulated performer it filmed."""

from __future__ import annotations

import math
import threading

import numpy as np

from livebridge.geometry.transforms import apply


class GroundTruthScore:
    """Contraction error and label swaps of solved frames against the performer's ground truth.

    Parameters
    ----------
    performer : livebridge.simulators.performer.Performer
        The performer the simulated rig films (a deterministic function of time).
    skip : int
        Solved frames ignored at the start (the alignment's first frame).
    swap_margin_mm : float
        A labelled marker counts as swapped when it lies closer to another marker's true position
        than to its own, by more than this margin.
    """

    def __init__(self, performer, skip: int = 0, swap_margin_mm: float = 0.5):
        self.performer = performer
        self.skip = skip
        self.swap_margin_mm = swap_margin_mm
        self._lock = threading.Lock()
        self.squared = 0.0
        self.count = 0
        self.frames = 0
        self.swaps = 0
        self.marker_frames = 0
        self.worst_abs = 0.0

    def truth(self, seq: int) -> tuple[np.ndarray, np.ndarray]:
        """True contractions (n_muscles,) and world marker positions (n_markers, 3) of frame ``seq``."""
        p = self.performer
        t = np.array([seq / p.fps])
        x = p.script(t)[0]
        head2world = p.head(t)[0]
        local = p.markers.marker_positions(p.basis, x)
        return x, apply(head2world, local)

    def __call__(self, frame) -> None:
        with self._lock:
            self.frames += 1
            if self.frames <= self.skip:
                return
        x_true, world_true = self.truth(frame.seq)
        error = np.asarray(frame.contractions) - x_true
        seen = np.isfinite(frame.positions_world).all(axis=1)
        swaps = 0
        if seen.any():
            labelled = frame.positions_world[seen]
            distances = np.linalg.norm(labelled[:, None, :] - world_true[None, :, :], axis=2)  # (n_seen, n)
            own = distances[np.arange(len(labelled)), np.flatnonzero(seen)]
            distances[np.arange(len(labelled)), np.flatnonzero(seen)] = np.inf
            swaps = int(np.sum(distances.min(axis=1) + self.swap_margin_mm < own))
        with self._lock:
            self.squared += float(np.sum(error**2))
            self.count += error.size
            self.worst_abs = max(self.worst_abs, float(np.max(np.abs(error))))
            self.swaps += swaps
            self.marker_frames += int(seen.sum())

    @property
    def rmse(self) -> float:
        return math.sqrt(self.squared / self.count) if self.count else math.nan

    def describe(self) -> str:
        """The summary line of a run."""
        return (f"contraction RMSE vs ground truth: {self.rmse:.4f} (worst {self.worst_abs:.3f}), "
                f"label swaps: {self.swaps}")


class ContractionScore:
    """Contraction error of solved frames against a truth looked up by the frame's ``seq``.

    For sources that say which moment of the performance a frame is (a simulated phone's frame number:
    :meth:`livebridge.simulators.iphone.SimulatedIPhone.truth`), so input latency and superseded packets do
    not count as error.

    Parameters
    ----------
    truth : callable
        ``truth(seq) -> ndarray (n_muscles,)``.
    skip : int
        Solved frames ignored at the start.
    """

    swaps = 0  # no markers to swap

    def __init__(self, truth, skip: int = 0):
        self.truth, self.skip = truth, skip
        self._lock = threading.Lock()
        self.squared = 0.0
        self.count = 0
        self.frames = 0
        self.worst_abs = 0.0

    def __call__(self, frame) -> None:
        with self._lock:
            self.frames += 1
            if self.frames <= self.skip:
                return
        error = np.asarray(frame.contractions) - self.truth(frame.seq)
        with self._lock:
            self.squared += float(np.sum(error**2))
            self.count += error.size
            self.worst_abs = max(self.worst_abs, float(np.max(np.abs(error))))

    @property
    def rmse(self) -> float:
        return math.sqrt(self.squared / self.count) if self.count else math.nan

    def describe(self) -> str:
        """The summary line of a run."""
        return f"contraction RMSE vs ground truth: {self.rmse:.4f} (worst {self.worst_abs:.3f})"

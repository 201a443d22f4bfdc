"""The front of the live pipeline: whatever turns a capture into :class:`~livebridge.runtime.frame.SolvedFrame`.

The pipeline (:mod:`livebridge.runtime.pipeline`) runs one front on its front thread, writes the servos
right after each frame it reads, and hands the frame to the outputs. Fronts: markers
(:class:`~livebridge.runtime.markers_front.MarkerFront`: cameras, detection, reconstruction, solve),
markerless (one camera, co-articulation regions) and Live Link Face (an iPhone's ARKit weights).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

from livebridge.runtime.frame import SolvedFrame


def shown(value: float, spec: str, unit: str = "") -> str:
    """A figure for the status line: ``value`` in ``spec`` (a format spec) with ``unit``, or ``none`` when nothing
    was measured (NaN: no frame of the window labelled yet, no render client)."""
    return f"{value:{spec}}{unit}" if math.isfinite(value) else "none"


@dataclass(frozen=True)
class FrontStats:
    """A front's figures for the run summary (its inputs: cameras, a phone).

    Attributes
    ----------
    inputs : int
        Inputs (cameras, packet receivers) the front reads.
    dead : tuple of str
        Inputs not delivering at the end.
    errors : tuple of (str, str)
        Inputs that failed and why.
    frames_skipped : tuple of (str, int)
        Per input with any: frames it skipped (a replay's damaged images, malformed packets).
    dropped : int
        Frames the front dropped before solving them (it was behind: newest wins).
    input_frame_drops : int
        Frames missing from an input (a camera's frame missing from a set, packets lost).
    attempts : int
        Frames the front worked on, solved or not.
    cpu_s : float
        CPU seconds of the front's own work (its thread, and its inputs' detection).
    input_cpu_s : float
        Of which the inputs' (e.g. per-camera detection).
    """

    inputs: int
    dead: tuple[str, ...] = ()
    errors: tuple[tuple[str, str], ...] = ()
    frames_skipped: tuple[tuple[str, int], ...] = ()
    dropped: int = 0
    input_frame_drops: int = 0
    attempts: int = 0
    cpu_s: float = 0.0
    input_cpu_s: float = 0.0


class Front(Protocol):
    """What turns a capture into solved frames (see the module docstring).

    ``read`` runs on the pipeline's front thread only; ``status`` and ``stats`` on the outputs thread.
    """

    kind: str
    """``"markers"``, ``"markerless"``, ``"livelink"``."""
    input_name: str
    """What one input is called in log lines (``"camera"``, ``"phone"``)."""
    realtime: bool
    """False: the front runs in step with the outputs (replays, unpaced simulators) and drops nothing."""
    muscle_names: tuple[str, ...]

    def warm_up(self) -> None:
        """Run every compiled per-frame kernel once, before any input starts (no stall mid-take)."""

    def start(self) -> None:
        """Start the inputs."""

    def read(self, timeout: float) -> SolvedFrame | None:
        """The next solved frame, or None when none came within ``timeout`` s.

        Raises an :class:`~livebridge.errors.InputError` when the front cannot go on for a reason the user
        must fix (e.g. the first labelling never happened): the pipeline ends with it.
        """

    @property
    def ended(self) -> bool:
        """Every input ended: :meth:`read` gives no more frames."""

    def done(self, frame: SolvedFrame) -> None:
        """The outputs finished ``frame`` (an unpaced front reads the next input now)."""

    def faults(self) -> dict[str, str]:
        """Inputs that failed so far and why (logged once each, when first seen)."""

    def status(self, summary) -> str:
        """The front's part of the live status line, given the pipeline's recent summary."""

    def waiting(self) -> str | None:
        """While no frame is solved yet: why (e.g. waiting for the first labelling), else None."""

    def stats(self) -> FrontStats:
        """Figures for the run summary."""

    def stop(self) -> None:
        """Stop the inputs (the pipeline has stopped reading)."""

"""What every front hands the outputs for one frame: :class:`SolvedFrame`, with its :class:`FrameTiming`.

The marker front fills the marker fields; a front that sees no markers (markerless, Live Link Face)
leaves them ``None`` and says how sure it is in :attr:`SolvedFrame.quality`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FrameTiming:
    """Monotonic seconds at each stage of one frame.

    Attributes
    ----------
    capture : float
        Mean mid-exposure time of the frames of the set (a packet's arrival for sources without exposure).
    complete : float
        The last input of the frame reached the host (the last camera frame, the packet).
    detected : float
        The last camera's detection of the set finished (= ``complete`` where nothing is detected).
    dequeued : float
        The front took the frame.
    reconstructed, solved : float
    servo : float
        Servo bytes written (NaN without servos).
    outputs : float
        Every output done.
    """

    capture: float
    complete: float
    detected: float
    dequeued: float
    reconstructed: float
    solved: float
    servo: float = math.nan
    outputs: float = math.nan


@dataclass(frozen=True, eq=False)
class SolvedFrame:
    """One frame through a front (what the servos and outputs receive).

    Attributes
    ----------
    seq : int
        Frame number of the input (of the first camera present; the packet's frame number).
    index : int
        Frame-set number from the synchroniser (the front's own count elsewhere).
    timing : FrameTiming
    contractions : ndarray, shape (n_muscles,)
        Finite, in [0, 1]: the front guarantees it.
    positions_model, positions_world, displacements : ndarray, shape (n_markers, 3), or None
        Marker fronts: labelled markers in the model frame (NaN unlabelled), in the world, and their
        displacements from the neutral. None for fronts without markers.
    region_errors : tuple of float
        RMS marker error (upper, lower), mm; NaN without markers.
    labelled_fraction : float
        NaN without markers.
    n_stray : int
    n_cameras : int
        Cameras that contributed a frame.
    held : ndarray of bool, shape (n_muscles,), or None
        Muscles held at their last value because what drives them was lost (a region, the LEDs).
    quality : tuple of (str, float)
        The front's figures of this frame for the status line and the render client (e.g. per-region
        confidence in [0, 1]).
    head_pose : ndarray, shape (4, 4), or None
        Head model -> world (mm), where the front measures the head (LEDs, the phone's head rotation).
    regions : tuple or None
        Per co-articulation region state (markerless fronts), for the 2D character.
    packet : LiveLinkPacket or None
        The phone's packet the frame was solved from (Live Link Face fronts), recorded with a take so that it
        can be solved again.
    """

    seq: int
    index: int
    timing: FrameTiming
    contractions: np.ndarray
    positions_model: np.ndarray | None = None
    positions_world: np.ndarray | None = None
    displacements: np.ndarray | None = None
    region_errors: tuple[float, float] = (math.nan, math.nan)
    labelled_fraction: float = math.nan
    n_stray: int = 0
    n_cameras: int = 0
    held: np.ndarray | None = None
    quality: tuple[tuple[str, float], ...] = ()
    head_pose: np.ndarray | None = None
    regions: tuple | None = None
    packet: object | None = None

"""A performer who holds a still, neutral face before performing (as an actor is asked to at the start of a take)."""

from __future__ import annotations

import numpy as np

from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.geometry.transforms import apply
from livebridge.simulators.performer import Performer, PerformerFrame


def scripted_performer(basis: Basis, markers: MarkerSet, fps: float, seed: int, script: str = "mixed",
                       lead_in_s: float = 0.0):
    """The :class:`~livebridge.simulators.performer.Performer` playing ``script`` (unpaced), after a lead-in
    of ``lead_in_s`` seconds (:class:`LeadIn`) when positive. A deterministic function of its arguments: the
    simulated rig films it and the ground-truth scoring rebuilds it."""
    performer = Performer(basis, markers, fps=fps, seed=seed, script=script, realtime=False)
    return LeadIn(performer, lead_in_s) if lead_in_s > 0 else performer


class LeadIn:
    """A performer who first holds a still, neutral face for ``lead_in_s`` seconds, then performs.

    As an actor is asked to at the start of a capture: the first labelling (which can take most of a
    second on a busy machine) must see the neutral face, and the frames right after it should too. Same
    interface as :class:`livebridge.simulators.performer.Performer` where the rig and the scoring use it
    (``basis``, ``markers``, ``fps``, ``script(t)``, ``head(t)``, ``frames()``).
    """

    def __init__(self, performer, lead_in_s: float):
        self.performer = performer
        self.basis, self.markers, self.fps = performer.basis, performer.markers, performer.fps
        self.lead_in_s = float(lead_in_s)

    def script(self, t) -> np.ndarray:
        """Contractions (n_times, n_muscles) at times ``t``: zero during the lead-in."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        x = self.performer.script(np.maximum(t - self.lead_in_s, 0.0))
        x[t < self.lead_in_s] = 0.0
        return x

    def head(self, t) -> np.ndarray:
        """``head2world`` (n_times, 4, 4) at times ``t``: the rest pose during the lead-in."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return self.performer.head(np.maximum(t - self.lead_in_s, 0.0))

    def frames(self, n_frames: int | None = None, chunk: int = 32):
        """:class:`~livebridge.simulators.performer.PerformerFrame` from 0, forever or ``n_frames``."""
        seq = 0
        while n_frames is None or seq < n_frames:
            count = chunk if n_frames is None else min(chunk, n_frames - seq)
            t = np.arange(seq, seq + count) / self.fps
            x, head2world = self.script(t), self.head(t)
            local = self.markers.marker_positions(self.basis, x)  # (count, n_markers, 3), model frame
            world = apply(head2world, local)
            for k in range(count):
                frame = PerformerFrame(seq + k, float(t[k]), x[k], head2world[k], world[k])
                for array in (frame.contractions, frame.head2world, frame.marker_positions):
                    array.setflags(write=False)
                yield frame
            seq += count

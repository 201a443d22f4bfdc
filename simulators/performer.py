"""A synthetic performer: smooth muscle contractions, rigid head motion and marker trajectories, with ground truth.

The performer plays a *script* of contractions ``x(t) (n_muscles,)`` in ``[0, 1]``:

- ``"training"``: each muscle in turn makes one isolated, smooth 0 -> 1 -> 0 sweep (raised cosine),
  with rests between, as in a training take (block of :data:`TRAINING_BLOCK_S` seconds per muscle);
- ``"everyday"``: overlapping compound expressions (smile, frown, surprise, disgust, sadness, pout,
  smirk, blinks, speech-like jaw and lip motion) with smooth onsets and offsets, in seeded blocks of
  :data:`EVERYDAY_BLOCK_S` seconds;
- ``"mixed"``: a training sweep of one muscle, then an everyday block, then the next muscle, ...

Several active expressions combine as ``1 - prod(1 - a_k)`` (each ``a_k`` in [0, 1]), which stays in
[0, 1] and is as smooth as its parts. Expressions are written with the Choe-Ko muscle names
(:data:`livebridge.face.basis.CHOE_KO_MUSCLES`); on a basis with other names the everyday script plays
random smooth combinations instead.

The head moves rigidly: a smooth sum of slow sinusoids (seeded) of a few centimetres of translation and
a few degrees of rotation about a pivot near the neck, ramped in over the first second. The world
frame is the model frame at rest: ``head2world`` is the identity at ``t = 0`` (and always, with
``head_motion=False``), and the first frame is the neutral face. Face markers follow the basis
(``markers.marker_positions(basis, x)``); head markers only follow the head.

Everything is a deterministic function of ``(seed, t)``: :func:`perform` (a whole performance at once)
and :class:`Performer` (a live frame stream, paced in real time or as fast as possible) give the same
frames for the same seed.
"""

from __future__ import annotations

import csv
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.geometry.transforms import apply
from livebridge.take.npz import Take

SCRIPTS = ("training", "everyday", "mixed")
TRAINING_BLOCK_S = 2.0  # per muscle: 0.25 s rest, 1.5 s sweep, 0.25 s rest
TRAINING_REST_S = 0.25
EVERYDAY_BLOCK_S = 6.0
HEAD_RAMP_S = 1.0

# Compound expressions: muscle -> peak contraction.
EXPRESSIONS = {
    "smile": {"zygomatic_major_L": 0.9, "zygomatic_major_R": 0.9, "orbicularis_oculi_L": 0.25,
              "orbicularis_oculi_R": 0.25, "risorius_L": 0.2, "risorius_R": 0.2, "levator_labii_L": 0.15,
              "levator_labii_R": 0.15, "jaw": 0.1},
    "frown": {"corrugator_L": 0.9, "corrugator_R": 0.9, "depressor_anguli_oris": 0.6, "lips_pressor": 0.3},
    "surprise": {"frontalis_L": 1.0, "frontalis_R": 1.0, "jaw": 0.45},
    "disgust": {"levator_labii_L": 0.85, "levator_labii_R": 0.85, "corrugator_L": 0.4, "corrugator_R": 0.4,
                "orbicularis_oculi_L": 0.2, "orbicularis_oculi_R": 0.2},
    "sad": {"depressor_anguli_oris": 0.8, "corrugator_L": 0.35, "corrugator_R": 0.35, "frontalis_L": 0.3,
            "frontalis_R": 0.3},
    "pout": {"orbicularis_oris": 0.9, "lips_pressor": 0.2},
    "press": {"lips_pressor": 0.9, "depressor_anguli_oris": 0.2},
    "smirk_L": {"zygomatic_major_L": 0.8, "risorius_L": 0.4},
    "smirk_R": {"zygomatic_major_R": 0.8, "risorius_R": 0.4},
    "wince_L": {"orbicularis_oculi_L": 0.7, "levator_labii_L": 0.4, "corrugator_L": 0.4},
    "wince_R": {"orbicularis_oculi_R": 0.7, "levator_labii_R": 0.4, "corrugator_R": 0.4},
}
BLINK = {"orbicularis_oculi_L": 1.0, "orbicularis_oculi_R": 1.0}
# Speech: the jaw opens per syllable; lips round or press between some syllables.
SPEECH_JAW = 0.45
SPEECH_LIPS = ("orbicularis_oris", "lips_pressor")


def _smoothstep(u: np.ndarray) -> np.ndarray:
    """Raised-cosine ramp 0 -> 1 over ``u`` in [0, 1], clamped outside."""
    u = np.clip(u, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * u)


def _envelope(t: np.ndarray, start: float, rise: float, hold: float, fall: float) -> np.ndarray:
    """Smooth trapezoid: 0 before ``start``, raised-cosine rise, hold at 1, raised-cosine fall, 0 after."""
    up = _smoothstep((t - start) / rise)
    down = 1.0 - _smoothstep((t - start - rise - hold) / fall)
    return up * down


@dataclass(frozen=True)
class _Event:
    """One expression in an everyday block: levels (n_muscles,) times a smooth envelope (times in block)."""

    levels: np.ndarray
    start: float
    rise: float
    hold: float
    fall: float
    syllable_hz: float = 0.0  # > 0: speech; the levels are modulated by syllables
    phase: float = 0.0

    @property
    def end(self) -> float:
        return self.start + self.rise + self.hold + self.fall

    def evaluate(self, t: np.ndarray) -> np.ndarray:
        """Activation, shape (n_times, n_muscles), at block times ``t (n_times,)``."""
        envelope = _envelope(t, self.start, self.rise, self.hold, self.fall)
        if self.syllable_hz > 0:
            envelope = envelope * (0.5 - 0.5 * np.cos(2 * np.pi * self.syllable_hz * (t - self.start) + self.phase))
        return envelope[:, None] * self.levels[None, :]


class ContractionScript:
    """Contraction curves ``x(t)`` for a basis's muscles; a deterministic function of ``(seed, t)``.

    Parameters
    ----------
    muscle_names : sequence of str, length n_muscles
    script : {"training", "everyday", "mixed"}
    seed : int
    """

    def __init__(self, muscle_names, script: str = "mixed", seed: int = 0):
        if script not in SCRIPTS:
            raise ValueError(f"script must be one of {SCRIPTS}, got {script!r}")
        self.muscle_names = tuple(muscle_names)
        self.script = script
        self.seed = int(seed)
        self._index = {name: i for i, name in enumerate(self.muscle_names)}
        known = set(EXPRESSIONS["smile"]) | set(EXPRESSIONS["frown"]) | set(EXPRESSIONS["surprise"])
        self._named = len(known & set(self.muscle_names)) >= 4
        self._blocks: dict[int, list[_Event]] = {}

    @property
    def n_muscles(self) -> int:
        return len(self.muscle_names)

    def _levels(self, expression: dict[str, float]) -> np.ndarray:
        levels = np.zeros(self.n_muscles)
        for name, level in expression.items():
            if name in self._index:
                levels[self._index[name]] = level
        return levels

    def _everyday_events(self, block: int) -> list[_Event]:
        """The seeded expressions of everyday block ``block`` (times relative to the block start)."""
        if block in self._blocks:
            return self._blocks[block]
        rng = np.random.default_rng([self.seed, block, 7])
        events: list[_Event] = []
        length = EVERYDAY_BLOCK_S
        for _ in range(int(rng.integers(2, 4))):  # expressions, possibly overlapping
            rise, fall = rng.uniform(0.25, 0.6, size=2)
            hold = rng.uniform(0.2, 1.5)
            start = rng.uniform(0.2, max(0.2, length - rise - hold - fall - 0.05))
            if self._named:
                name = list(EXPRESSIONS)[int(rng.integers(len(EXPRESSIONS)))]
                levels = self._levels(EXPRESSIONS[name]) * rng.uniform(0.6, 1.0)
            else:
                levels = np.zeros(self.n_muscles)
                chosen = rng.choice(self.n_muscles, size=min(3, self.n_muscles), replace=False)
                levels[chosen] = rng.uniform(0.4, 1.0, size=len(chosen))
            events.append(_Event(levels, start, rise, hold, fall))
        if self._named:
            # speech: syllables at 3-5 Hz open the jaw, lips round or press in between
            duration = rng.uniform(1.2, 2.5)
            start = rng.uniform(0.2, length - duration - 0.05)
            jaw = self._levels({"jaw": SPEECH_JAW * rng.uniform(0.6, 1.0)})
            hz = rng.uniform(3.0, 5.0)
            events.append(_Event(jaw, start, 0.15, duration - 0.3, 0.15, syllable_hz=hz))
            lips = self._levels({SPEECH_LIPS[int(rng.integers(2))]: rng.uniform(0.3, 0.6)})
            events.append(_Event(lips, start, 0.15, duration - 0.3, 0.15, syllable_hz=hz, phase=np.pi))
            # blinks: fast, full closure
            for _ in range(int(rng.integers(1, 3))):
                start = rng.uniform(0.1, length - 0.35)
                events.append(_Event(self._levels(BLINK), start, 0.1, 0.04, 0.18))
        self._blocks[block] = events
        if len(self._blocks) > 64:
            self._blocks.pop(next(iter(self._blocks)))
        return events

    def _everyday(self, block: int, t: np.ndarray) -> np.ndarray:
        """Contractions (n_times, n_muscles) of everyday block ``block`` at block times ``t``."""
        rest = np.ones((len(t), self.n_muscles))
        for event in self._everyday_events(block):
            rest *= 1.0 - event.evaluate(t)
        return 1.0 - rest

    def _training(self, muscle: int, t: np.ndarray) -> np.ndarray:
        """Contractions (n_times, n_muscles) of one isolated sweep of ``muscle`` at block times ``t``."""
        x = np.zeros((len(t), self.n_muscles))
        sweep = TRAINING_BLOCK_S - 2 * TRAINING_REST_S
        u = np.clip((t - TRAINING_REST_S) / sweep, 0.0, 1.0)
        x[:, muscle] = 0.5 - 0.5 * np.cos(2 * np.pi * u)
        return x

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Contractions at times ``t``.

        Parameters
        ----------
        t : ndarray, shape (n_times,)
            Seconds since the start of the performance (>= 0).

        Returns
        -------
        ndarray, shape (n_times, n_muscles), values in [0, 1]
        """
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        x = np.zeros((len(t), self.n_muscles))
        if self.script == "training":
            period, kinds = TRAINING_BLOCK_S, ("training",)
        elif self.script == "everyday":
            period, kinds = EVERYDAY_BLOCK_S, ("everyday",)
        else:
            period, kinds = TRAINING_BLOCK_S + EVERYDAY_BLOCK_S, ("training", "everyday")
        cycle = np.floor(t / period).astype(np.int64)
        local = t - cycle * period
        for c in np.unique(cycle):
            rows = np.flatnonzero(cycle == c)
            tc = local[rows]
            if kinds == ("training",):
                x[rows] = self._training(int(c) % self.n_muscles, tc)
            elif kinds == ("everyday",):
                x[rows] = self._everyday(int(c), tc)
            else:
                first = tc < TRAINING_BLOCK_S
                x[rows[first]] = self._training(int(c) % self.n_muscles, tc[first])
                x[rows[~first]] = self._everyday(int(c), tc[~first] - TRAINING_BLOCK_S)
        return np.clip(x, 0.0, 1.0)


# Combined gestures a markerless training take adds after the isolated ones (CoArt trains them as
# pseudo-muscles of their co-articulation region): muscle -> level at the gesture's peak. The paper names
# the centre frontalis with the corrugator (a sad brow); the others are the combinations the everyday
# expressions make within one region.
COMBINED_GESTURES = {
    "frontalis+corrugator": {"frontalis_L": 1.0, "frontalis_R": 1.0, "corrugator_L": 1.0, "corrugator_R": 1.0},
    "corrugator+orbicularis_oculi": {"corrugator_L": 1.0, "corrugator_R": 1.0, "orbicularis_oculi_L": 0.7,
                                     "orbicularis_oculi_R": 0.7},
    "levator_labii+corrugator": {"levator_labii_L": 1.0, "levator_labii_R": 1.0, "corrugator_L": 0.5,
                                 "corrugator_R": 0.5},
    "zygomatic+orbicularis_oculi": {"zygomatic_major_L": 1.0, "zygomatic_major_R": 1.0,
                                    "orbicularis_oculi_L": 0.3, "orbicularis_oculi_R": 0.3},
    "zygomatic+risorius": {"zygomatic_major_L": 1.0, "zygomatic_major_R": 1.0, "risorius_L": 0.5,
                           "risorius_R": 0.5},
    "depressor+lips_pressor": {"depressor_anguli_oris": 1.0, "lips_pressor": 0.5},
    "orbicularis_oris+lips_pressor": {"orbicularis_oris": 1.0, "lips_pressor": 0.4},
    "frontalis+jaw": {"frontalis_L": 1.0, "frontalis_R": 1.0, "jaw": 0.6},
}
GESTURE_SCRIPTS = ("gestures",)
FACE_SCRIPTS = SCRIPTS + GESTURE_SCRIPTS
"""Scripts the face-video simulator plays: the marker rig's and ``"gestures"`` (:class:`GestureScript`)."""


class GestureScript:
    """A markerless training take: every muscle's isolated gesture in turn, then the combined gestures.

    Each gesture is one block of :data:`TRAINING_BLOCK_S` seconds: neutral for :data:`TRAINING_REST_S`, a
    smooth neutral -> full -> neutral sweep (raised cosine), neutral again; combined gestures sweep their
    muscles together in the proportions of :data:`COMBINED_GESTURES` (those whose muscles the basis lacks
    are left out). After the last gesture the take starts over. Same interface as
    :class:`ContractionScript` (``muscle_names``, ``n_muscles``, ``__call__(t)``), plus the gesture labels.

    Parameters
    ----------
    muscle_names : sequence of str, length n_muscles
    seed : int
        Unused (the take is the same for every seed); kept for the common signature.
    """

    def __init__(self, muscle_names, seed: int = 0):
        self.muscle_names = tuple(muscle_names)
        self.script = "gestures"
        self.seed = int(seed)
        index = {name: i for i, name in enumerate(self.muscle_names)}
        names, levels = [], []
        for i, name in enumerate(self.muscle_names):
            names.append(name)
            levels.append(np.eye(len(self.muscle_names))[i])
        for name, combination in COMBINED_GESTURES.items():
            if all(m in index for m in combination):
                level = np.zeros(len(self.muscle_names))
                for muscle, value in combination.items():
                    level[index[muscle]] = value
                names.append(name)
                levels.append(level)
        self.gesture_names = tuple(names)
        self.gesture_levels = np.array(levels).reshape(len(names), len(self.muscle_names))

    @property
    def n_muscles(self) -> int:
        return len(self.muscle_names)

    @property
    def duration(self) -> float:
        """Seconds of one pass through all gestures."""
        return TRAINING_BLOCK_S * len(self.gesture_names)

    def gesture_at(self, t: np.ndarray) -> np.ndarray:
        """Index into ``gesture_names`` of the gesture whose block holds each time ``t (n_times,)``; -1 in the
        neutral rests between sweeps. Shape (n_times,)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        block = np.floor(t / TRAINING_BLOCK_S).astype(np.int64)
        local = t - block * TRAINING_BLOCK_S
        sweeping = (local > TRAINING_REST_S) & (local < TRAINING_BLOCK_S - TRAINING_REST_S)
        return np.where(sweeping, block % len(self.gesture_names), -1)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Contractions at times ``t (n_times,)``, shape (n_times, n_muscles), values in [0, 1]."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        block = np.floor(t / TRAINING_BLOCK_S).astype(np.int64) % len(self.gesture_names)
        local = t - np.floor(t / TRAINING_BLOCK_S) * TRAINING_BLOCK_S
        sweep = TRAINING_BLOCK_S - 2 * TRAINING_REST_S
        u = np.clip((local - TRAINING_REST_S) / sweep, 0.0, 1.0)
        envelope = 0.5 - 0.5 * np.cos(2 * np.pi * u)
        return np.clip(envelope[:, None] * self.gesture_levels[block], 0.0, 1.0)


def contraction_script(muscle_names, script: str = "mixed", seed: int = 0):
    """The script ``script`` (one of :data:`FACE_SCRIPTS`) for a basis's muscles: a :class:`GestureScript`
    for ``"gestures"``, else a :class:`ContractionScript`."""
    if script in GESTURE_SCRIPTS:
        return GestureScript(muscle_names, seed)
    return ContractionScript(muscle_names, script, seed)


def head_pivot(basis: Basis) -> np.ndarray:
    """A pivot near the neck for head rotation, shape (3,): below and behind the face's centre."""
    low, high = basis.neutral.min(axis=0), basis.neutral.max(axis=0)
    centre = 0.5 * (low + high)
    return np.array([centre[0], low[1] + 0.2 * (high[1] - low[1]), low[2] + 0.2 * (high[2] - low[2])])


class HeadMotion:
    """Smooth rigid head motion ``head2world(t)``, identity at ``t = 0``; deterministic in ``seed``.

    Parameters
    ----------
    pivot : ndarray, shape (3,)
        Rotation centre in the model frame (mm), near the neck.
    seed : int
    translation_mm : float
        Peak translation per axis (a few centimetres).
    rotation_deg : float
        Peak rotation per axis (a few degrees).
    """

    def __init__(self, pivot: np.ndarray, seed: int = 0, translation_mm: float = 25.0, rotation_deg: float = 6.0):
        rng = np.random.default_rng([int(seed), 11])
        self.pivot = np.asarray(pivot, dtype=np.float64)
        n_terms = 3
        # per axis (6: tx ty tz rx ry rz) and term: frequency (Hz), phase, amplitude share
        self._freq = rng.uniform(0.05, 0.4, size=(6, n_terms))
        self._phase = rng.uniform(0, 2 * np.pi, size=(6, n_terms))
        share = rng.dirichlet(np.ones(n_terms), size=6)
        peak = np.array([translation_mm] * 3 + [np.deg2rad(rotation_deg)] * 3)
        self._amplitude = share * peak[:, None] * rng.uniform(0.5, 1.0, size=(6, 1))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Head poses at times ``t (n_times,)``: ``head2world``, shape (n_times, 4, 4)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        angle = 2 * np.pi * self._freq[None] * t[:, None, None] + self._phase[None]
        motion = (self._amplitude[None] * (np.sin(angle) - np.sin(self._phase[None]))).sum(axis=2)  # (n, 6)
        motion *= _smoothstep(t / HEAD_RAMP_S)[:, None]
        rotation = Rotation.from_rotvec(motion[:, 3:]).as_matrix()  # (n, 3, 3)
        head2world = np.tile(np.eye(4), (len(t), 1, 1))
        head2world[:, :3, :3] = rotation
        # rotate about the pivot, then translate: p' = R (p - c) + c + d
        head2world[:, :3, 3] = self.pivot - rotation @ self.pivot + motion[:, :3]
        return head2world


def _still(t: np.ndarray) -> np.ndarray:
    return np.tile(np.eye(4), (len(np.atleast_1d(t)), 1, 1))


@dataclass(frozen=True, eq=False)
class Performance:
    """A synthetic performance with ground truth.

    Attributes
    ----------
    t : ndarray, shape (n_frames,)
        Seconds since the start.
    contractions : ndarray, shape (n_frames, n_muscles)
        Ground-truth contractions in [0, 1].
    head2world : ndarray, shape (n_frames, 4, 4)
        Ground-truth head pose; the world frame is the model frame at rest.
    marker_positions : ndarray, shape (n_frames, n_markers, 3)
        Marker positions in the world frame, mm.
    marker_displacements : ndarray, shape (n_frames, n_markers, 3)
        Marker displacement from neutral in the model (head) frame, mm (zero for head markers).
    muscle_names : tuple of str
    marker_names : tuple of str
    fps : float
    """

    t: np.ndarray
    contractions: np.ndarray
    head2world: np.ndarray
    marker_positions: np.ndarray
    marker_displacements: np.ndarray
    muscle_names: tuple[str, ...]
    marker_names: tuple[str, ...]
    fps: float

    @property
    def n_frames(self) -> int:
        return len(self.t)

    def to_take(self) -> Take:
        """The performance as a :class:`livebridge.take.npz.Take` with its ground truth."""
        return Take(t=self.t, marker_names=self.marker_names, displacements=self.marker_displacements,
                    positions=self.marker_positions, contractions=self.contractions,
                    muscle_names=self.muscle_names, head2world=self.head2world, fps=self.fps)

    def save_csv(self, path: str | Path) -> None:
        """Write one row per frame as CSV.

        Columns, in order: ``frame``, ``t`` (s); ``x.<muscle>`` per muscle (contraction);
        ``head2world.r<i><j>`` (rotation, row-major) and ``head2world.t<i>`` (translation, mm);
        ``<marker>.x``, ``<marker>.y``, ``<marker>.z`` per marker (world position, mm).
        """
        header = ["frame", "t"] + [f"x.{name}" for name in self.muscle_names]
        header += [f"head2world.r{i}{j}" for i in range(3) for j in range(3)]
        header += [f"head2world.t{i}" for i in range(3)]
        header += [f"{name}.{axis}" for name in self.marker_names for axis in "xyz"]
        table = np.concatenate([
            np.arange(self.n_frames)[:, None], self.t[:, None], self.contractions,
            self.head2world[:, :3, :3].reshape(self.n_frames, 9), self.head2world[:, :3, 3],
            self.marker_positions.reshape(self.n_frames, -1),
        ], axis=1)
        with Path(path).open("w", newline="") as stream:
            writer = csv.writer(stream)
            writer.writerow(header)
            for row in table:
                writer.writerow([str(int(row[0]))] + [repr(float(v)) for v in row[1:]])


@dataclass(frozen=True, eq=False)
class PerformerFrame:
    """One live frame of the performer.

    Attributes
    ----------
    seq : int
        Frame number from 0.
    t : float
        Performance time ``seq / fps`` in seconds (in real time, emitted at ``start + t`` on ``time.monotonic``).
    contractions : ndarray, shape (n_muscles,)
    head2world : ndarray, shape (4, 4)
    marker_positions : ndarray, shape (n_markers, 3)
        World positions, mm.
    """

    seq: int
    t: float
    contractions: np.ndarray
    head2world: np.ndarray
    marker_positions: np.ndarray


class Performer:
    """A live synthetic performer: a stream of :class:`PerformerFrame`.

    Parameters
    ----------
    basis : Basis
    markers : MarkerSet
    fps : float
    seed : int
    script : {"training", "everyday", "mixed"}
    realtime : bool
        True: frame ``seq`` is emitted no earlier than ``start + seq / fps`` on ``time.monotonic``;
        False: as fast as the CPU allows.
    head_motion : bool
    """

    def __init__(self, basis: Basis, markers: MarkerSet, fps: float = 60.0, seed: int = 0, script: str = "mixed",
                 realtime: bool = True, head_motion: bool = True):
        if not fps > 0:
            raise ValueError(f"fps must be positive, got {fps}")
        markers.check_mesh(len(basis.triangles))
        self.basis, self.markers, self.fps, self.realtime = basis, markers, float(fps), realtime
        self.script = ContractionScript(basis.names, script, seed)
        self.head = HeadMotion(head_pivot(basis), seed) if head_motion else _still
        self._neutral = markers.neutral_positions(basis)  # (n_markers, 3)
        self._displacement = markers.displacement_matrix(basis)  # (n_markers, M, 3)

    def _frames_at(self, seq: np.ndarray):
        """Ground truth for frame numbers ``seq (n,)``: t, contractions, head2world, model displacements, world."""
        t = np.asarray(seq, dtype=np.float64) / self.fps
        x = self.script(t)
        head2world = self.head(t)
        displacements = np.einsum("nm,kmd->nkd", x, self._displacement)
        world = apply(head2world, self._neutral[None] + displacements)
        return t, x, head2world, displacements, world

    def performance(self, n_frames: int) -> Performance:
        """The first ``n_frames`` frames at once."""
        t, x, head2world, displacements, world = self._frames_at(np.arange(int(n_frames)))
        return Performance(t, x, head2world, world, displacements, self.basis.names, self.markers.names, self.fps)

    def frames(self, n_frames: int | None = None, chunk: int = 32) -> Iterator[PerformerFrame]:
        """Yield frames from 0, forever or ``n_frames`` of them; paced when ``realtime``."""
        start = time.monotonic()
        seq = 0
        while n_frames is None or seq < n_frames:
            count = chunk if n_frames is None else min(chunk, n_frames - seq)
            t, x, head2world, _, world = self._frames_at(np.arange(seq, seq + count))
            for k in range(count):
                if self.realtime:
                    delay = start + t[k] - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                frame = PerformerFrame(seq + k, float(t[k]), x[k], head2world[k], world[k])
                for array in (frame.contractions, frame.head2world, frame.marker_positions):
                    array.setflags(write=False)
                yield frame
            seq += count


def perform(basis: Basis, markers: MarkerSet, n_frames: int, fps: float = 60.0, seed: int = 0,
            script: str = "mixed", head_motion: bool = True) -> Performance:
    """A synthetic performance with ground truth (see the module docstring).

    Parameters
    ----------
    basis : Basis
    markers : MarkerSet
    n_frames : int
    fps : float
    seed : int
    script : {"training", "everyday", "mixed"}
    head_motion : bool
        False keeps ``head2world`` the identity.

    Returns
    -------
    Performance
    """
    return Performer(basis, markers, fps, seed, script, realtime=False, head_motion=head_motion).performance(n_frames)

"""Takes: per-frame marker data (and ground truth when known) on disk.

File format: one ``.npz`` (``numpy.savez_compressed``) with

- ``manifest``: a JSON string ``{"format": "livebridge-take", "version": 1,
  "marker_names": [...], "muscle_names": [...] or null, "fps": float or null}``;
- ``t`` float64 ``(n_frames,)``: seconds on one monotonic clock;
- ``displacements`` float64 ``(n_frames, n_markers, 3)``: marker displacement
  from neutral in the face model frame, mm, NaN where not seen; and/or
- ``positions`` float64 ``(n_frames, n_markers, 3)``: marker positions in the
  capture (world) frame, mm, NaN where not seen;
- optional ``contractions`` float64 ``(n_frames, n_muscles)``: ground truth;
- optional ``head2world`` float64 ``(n_frames, 4, 4)``: ground-truth head pose.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError

TAKE_FORMAT = "livebridge-take"
TAKE_VERSION = 1
_ARRAYS = ("displacements", "positions", "contractions", "head2world")


@dataclass(frozen=True, eq=False)
class Take:
    """A recorded or simulated take.

    Attributes
    ----------
    t : ndarray, shape (n_frames,)
    marker_names : tuple of str, length n_markers
    displacements : ndarray, shape (n_frames, n_markers, 3), optional
    positions : ndarray, shape (n_frames, n_markers, 3), optional
    contractions : ndarray, shape (n_frames, n_muscles), optional
    muscle_names : tuple of str, optional
    head2world : ndarray, shape (n_frames, 4, 4), optional
    fps : float, optional
    """

    t: np.ndarray
    marker_names: tuple[str, ...]
    displacements: np.ndarray | None = None
    positions: np.ndarray | None = None
    contractions: np.ndarray | None = None
    muscle_names: tuple[str, ...] | None = None
    head2world: np.ndarray | None = None
    fps: float | None = None

    def __post_init__(self):
        n_frames, n_markers = len(self.t), len(self.marker_names)
        expected = {
            "displacements": (n_frames, n_markers, 3),
            "positions": (n_frames, n_markers, 3),
            "head2world": (n_frames, 4, 4),
        }
        if self.displacements is None and self.positions is None:
            raise InputError("a take needs displacements or positions")
        for name, shape in expected.items():
            value = getattr(self, name)
            if value is not None and np.shape(value) != shape:
                raise InputError(f"shape {np.shape(value)}, expected {shape}", field=name)
        if self.contractions is not None:
            n_muscles = len(self.muscle_names) if self.muscle_names else np.shape(self.contractions)[-1]
            if np.shape(self.contractions) != (n_frames, n_muscles):
                raise InputError(f"shape {np.shape(self.contractions)}, expected {(n_frames, n_muscles)}",
                                 field="contractions")

    @property
    def n_frames(self) -> int:
        return len(self.t)

    def save(self, path: str | Path) -> None:
        """Write the take as one ``.npz`` (format in the module docstring)."""
        manifest = {
            "format": TAKE_FORMAT, "version": TAKE_VERSION, "marker_names": list(self.marker_names),
            "muscle_names": list(self.muscle_names) if self.muscle_names else None, "fps": self.fps,
        }
        arrays = {name: np.asarray(getattr(self, name), dtype=np.float64)
                  for name in _ARRAYS if getattr(self, name) is not None}
        with Path(path).open("wb") as stream:
            np.savez_compressed(stream, manifest=np.array(json.dumps(manifest)),
                                t=np.asarray(self.t, dtype=np.float64), **arrays)

    @classmethod
    def load(cls, path: str | Path) -> Take:
        """Read a take written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise InputError("take file not found", path)
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files}
        except (OSError, ValueError) as error:
            raise InputError(f"not a livebridge take .npz ({error})", path) from None
        if "manifest" not in arrays or "t" not in arrays:
            raise InputError("missing 'manifest' or 't'", path)
        manifest = json.loads(str(arrays["manifest"]))
        if manifest.get("format") != TAKE_FORMAT:
            raise InputError(f"format must be {TAKE_FORMAT!r}", path, "format")
        if manifest.get("version", 0) > TAKE_VERSION:
            raise InputError(f"version {manifest['version']} is newer than this livebridge reads", path, "version")
        muscle_names = manifest.get("muscle_names")
        try:
            return cls(
                t=arrays["t"], marker_names=tuple(manifest["marker_names"]),
                muscle_names=tuple(muscle_names) if muscle_names else None, fps=manifest.get("fps"),
                **{name: arrays.get(name) for name in _ARRAYS},
            )
        except InputError as error:
            raise InputError(error.message, path, error.field) from None

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
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.npzio import read_npz

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

    def save(self, path) -> None:
        """Write the take as one ``.npz`` (format in the module docstring) to the file ``path`` (str or Path) or
        into an open binary stream."""
        manifest = {
            "format": TAKE_FORMAT, "version": TAKE_VERSION, "marker_names": list(self.marker_names),
            "muscle_names": list(self.muscle_names) if self.muscle_names else None, "fps": self.fps,
        }
        arrays = {name: np.asarray(getattr(self, name), dtype=np.float64)
                  for name in _ARRAYS if getattr(self, name) is not None}
        if hasattr(path, "write"):
            np.savez_compressed(path, manifest=np.array(json.dumps(manifest)), t=np.asarray(self.t, dtype=np.float64),
                                **arrays)
            return
        with Path(path).open("wb") as stream:
            self.save(stream)

    @classmethod
    def load(cls, path: str | Path) -> Take:
        """Read a take written by :meth:`save`; anything malformed raises :class:`InputError` naming the file
        and the array or manifest field (checks: :func:`_read_arrays`, :func:`_check_manifest`,
        :func:`_check_arrays`)."""
        path = Path(path)
        arrays = _read_arrays(path)
        manifest = _check_manifest(path, arrays.pop("manifest"))
        arrays = _check_arrays(path, arrays)
        try:
            return cls(marker_names=tuple(manifest["marker_names"]), muscle_names=manifest["muscle_names"],
                       fps=manifest["fps"], **arrays)
        except InputError as error:
            raise InputError(error.message, path, error.field) from None


_MANIFEST_KEYS = {"format", "version", "marker_names", "muscle_names", "fps"}


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path`` (no pickles); a missing, truncated or foreign file, or one without
    ``manifest`` or ``t``, raises."""
    arrays = read_npz(path, "livebridge take", ("manifest", "t"), others=True)
    unknown = sorted(set(arrays) - {"manifest", "t", *_ARRAYS})
    if unknown:
        raise InputError(f"unknown array(s) {', '.join(unknown)}; known: manifest, t, {', '.join(_ARRAYS)}",
                         path, unknown[0])
    return arrays


def _check_manifest(path: Path, raw: np.ndarray) -> dict:
    """The manifest (JSON text in a 0-d string array), every field checked; names tuples, fps float or None."""
    if raw.ndim != 0 or raw.dtype.kind != "U":
        raise InputError(f"expected one JSON string, got a {raw.dtype} array of shape {raw.shape}", path,
                         "manifest")
    try:
        manifest = json.loads(str(raw))
    except ValueError as error:
        raise InputError(f"not valid JSON ({error})", path, "manifest") from None
    if not isinstance(manifest, dict):
        raise InputError(f"expected a JSON object, got {type(manifest).__name__}", path, "manifest")
    unknown = sorted(set(manifest) - _MANIFEST_KEYS)
    if unknown:
        raise InputError(f"unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(_MANIFEST_KEYS))}", path,
                         f"manifest.{unknown[0]}")
    if manifest.get("format") != TAKE_FORMAT:
        raise InputError(f"format must be {TAKE_FORMAT!r}, got {manifest.get('format')!r}", path, "manifest.format")
    version = manifest.get("version")
    if type(version) is not int or not 1 <= version:
        raise InputError(f"expected a positive integer, got {version!r}", path, "manifest.version")
    if version > TAKE_VERSION:
        raise InputError(f"version {version} is newer than this livebridge reads", path, "manifest.version")
    marker_names = _names(path, manifest, "marker_names")
    if not marker_names:
        raise InputError("expected a non-empty list of marker names", path, "manifest.marker_names")
    fps = manifest.get("fps")
    if fps is not None and (type(fps) not in (int, float) or not math.isfinite(fps) or fps <= 0):
        raise InputError(f"expected a positive finite number or null, got {fps!r}", path, "manifest.fps")
    return {"marker_names": marker_names, "muscle_names": _names(path, manifest, "muscle_names") or None,
            "fps": None if fps is None else float(fps)}


def _names(path: Path, manifest: dict, key: str) -> tuple[str, ...] | None:
    """A list of distinct non-empty strings (or null) from the manifest."""
    names = manifest.get(key)
    if names is None:
        return None
    if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
        raise InputError(f"expected a list of non-empty strings, got {names!r:.80}", path, f"manifest.{key}")
    if len(set(names)) != len(names):
        twice = sorted({n for n in names if names.count(n) > 1})
        raise InputError(f"name(s) given twice: {', '.join(twice)}", path, f"manifest.{key}")
    return tuple(names)


def _check_arrays(path: Path, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The data arrays as float64, numeric and of the right rank; ``t`` finite and non-decreasing, the others
    finite or NaN (unseen). Shapes against each other: :meth:`Take.__post_init__`."""
    ranks = {"t": 1, "displacements": 3, "positions": 3, "contractions": 2, "head2world": 3}
    checked = {}
    for name, array in arrays.items():
        if array.dtype.kind not in "fiu":
            raise InputError(f"expected numbers, got dtype {array.dtype}", path, name)
        if array.ndim != ranks[name]:
            raise InputError(f"expected {ranks[name]} dimensions, got shape {array.shape}", path, name)
        array = array.astype(np.float64)
        if np.isinf(array).any():
            raise InputError("infinite values", path, name)
        checked[name] = array
    t = checked["t"]
    if not len(t):
        raise InputError("no frames", path, "t")
    if np.isnan(t).any() or (np.diff(t) < 0).any():
        raise InputError("times must be finite and non-decreasing", path, "t")
    return checked

"""The markerless head rig: four bright (infrared) LEDs on an empty glasses frame fixed to the head.

Its geometry is four named LED positions in the head (model) frame, mm, read from a small TOML file::

    # livebridge head rig: LED positions in the head frame, mm (+y up, +z out of the face)
    [leds]
    upper_L = [60.3, 44.0, 82.1]
    upper_R = [-60.3, 44.0, 82.1]
    lower_L = [22.5, 16.0, 99.0]
    lower_R = [-22.5, 16.0, 99.0]

:func:`default_head_rig` fits such a frame to a face (its eye corners when known, else its proportions);
:func:`frame_polyline` gives the frame's rims and temples as 3D points for drawing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.tomlio import load_toml, require, save_toml

N_LEDS = 4
MIN_SPACING_MM = 5.0  # two LEDs closer than this would merge into one blob
LED_DIAMETER_MM = 5.0
CLEARANCE_MM = 8.0  # the frame stands at least this far in front of the skin


@dataclass(frozen=True, eq=False)
class HeadRig:
    """Four LEDs fixed to the head.

    Attributes
    ----------
    names : tuple of str, length 4
    positions : ndarray, shape (4, 3)
        LED centres in the head frame, mm.
    """

    names: tuple[str, ...]
    positions: np.ndarray

    def __post_init__(self):
        positions = np.asarray(self.positions, dtype=np.float64)
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "names", tuple(self.names))
        _check_geometry(self.names, positions, None)
        positions.setflags(write=False)

    def save(self, path: str | Path) -> None:
        """Write the rig as a head-rig TOML file (see the module docstring)."""
        save_toml(path, {"leds": {name: [float(v) for v in p] for name, p in zip(self.names, self.positions)}})


def _check_geometry(names: tuple[str, ...], positions: np.ndarray, path) -> None:
    """Four distinct finite LEDs, not on one line (a pose needs them spread out)."""
    if positions.shape != (N_LEDS, 3) or len(names) != N_LEDS:
        raise InputError(f"a head rig has exactly {N_LEDS} LEDs, got {len(names)}", path, "leds")
    if len(set(names)) != N_LEDS:
        raise InputError(f"LED names repeat: {names}", path, "leds")
    for name, position in zip(names, positions):
        if not np.isfinite(position).all():
            raise InputError(f"LED position must be finite, got {position.tolist()}", path, f"leds.{name}")
    for i in range(N_LEDS):
        for j in range(i + 1, N_LEDS):
            if np.linalg.norm(positions[i] - positions[j]) < MIN_SPACING_MM:
                raise InputError(f"LEDs {names[i]} and {names[j]} are closer than {MIN_SPACING_MM:g} mm", path,
                                 f"leds.{names[j]}")
    spread = np.linalg.svd(positions - positions.mean(axis=0), compute_uv=False)
    if spread[1] < MIN_SPACING_MM / 2:
        raise InputError("the LEDs lie on one line: a head pose needs them spread over a plane", path, "leds")


def load_head_rig(path: str | Path) -> HeadRig:
    """Read a head-rig TOML file; a malformed one raises :class:`InputError` naming the file and the field."""
    data = load_toml(path)
    leds = require(data, "leds", dict, path)
    names, positions = [], []
    for name, value in leds.items():
        field = f"leds.{name}"
        if (not isinstance(value, list) or len(value) != 3
                or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)):
            raise InputError(f"expected a list of 3 numbers (x, y, z in mm), got {value!r}", path, field)
        if not all(math.isfinite(v) for v in value):
            raise InputError(f"expected finite numbers, got {value!r}", path, field)
        names.append(name)
        positions.append([float(v) for v in value])
    positions_array = np.array(positions, dtype=np.float64).reshape(-1, 3)
    _check_geometry(tuple(names), positions_array, path)
    return HeadRig(tuple(names), positions_array)


def _eye_corners(neutral: np.ndarray, features: dict[str, np.ndarray] | None) -> dict[str, np.ndarray]:
    """Inner and outer eye corners ``{'inner_L', 'outer_L', 'inner_R', 'outer_R'}``: the landmarks when given,
    else guessed from the face's proportions (eyes a little above the middle of a head-and-neck mesh)."""
    names = ("eye_inner_L", "eye_outer_L", "eye_inner_R", "eye_outer_R")
    if features and all(n in features for n in names):
        return {n[4:]: np.asarray(features[n], dtype=np.float64) for n in names}
    low, high = neutral.min(axis=0), neutral.max(axis=0)
    centre_x, height = 0.5 * (low[0] + high[0]), high[1] - low[1]
    half = 0.5 * (high[0] - low[0])
    eye_y = low[1] + 0.63 * height
    front = neutral[np.abs(neutral[:, 1] - eye_y) < 0.05 * height]
    corners = {}
    for side, sign in (("L", 1.0), ("R", -1.0)):
        for name, reach in (("inner", 0.25), ("outer", 0.6)):
            x = centre_x + sign * reach * half
            near = front[np.abs(front[:, 0] - x) < 0.05 * half]
            z = near[:, 2].max() if len(near) else high[2]
            corners[f"{name}_{side}"] = np.array([x, eye_y, z])
    return corners


def _skin_depth(neutral: np.ndarray, x: float, y: float) -> float:
    """Front-most z of the skin near ``(x, y)`` (within 4 mm)."""
    near = neutral[np.hypot(neutral[:, 0] - x, neutral[:, 1] - y) < 4.0]
    return float(near[:, 2].max()) if len(near) else float(neutral[:, 2].max())


def default_head_rig(neutral: np.ndarray, features: dict[str, np.ndarray] | None = None) -> HeadRig:
    """A glasses frame fitted to a face: LEDs at the upper outer corners and the lower inner corners of the
    rims (the two pairs at different depths, so the pose is well posed), ``CLEARANCE_MM`` in front of the skin.

    Parameters
    ----------
    neutral : ndarray, shape (n_vertices, 3)
    features : dict of str to ndarray (3,), optional
        Landmarks; the eye corners (``eye_inner_L`` ...) place the frame.
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    eyes = _eye_corners(neutral, features)
    eye_y = float(np.mean([p[1] for p in eyes.values()]))
    lens_z = max(p[2] for p in eyes.values()) + 14.0  # lenses ~12 mm in front of the eyes
    names, positions = [], []
    for side, sign in (("L", 1.0), ("R", -1.0)):
        outer, inner = eyes[f"outer_{side}"], eyes[f"inner_{side}"]
        for name, x, y, back in (("upper", outer[0] + sign * 8.0, eye_y + 8.0, 10.0),
                                 ("lower", inner[0] + sign * 4.0, eye_y - 12.0, 0.0)):
            z = max(lens_z - back, _skin_depth(neutral, x, y) + CLEARANCE_MM)
            names.append(f"{name}_{side}")
            positions.append([x, y, z])
    order = [names.index(n) for n in ("upper_L", "upper_R", "lower_L", "lower_R")]
    return HeadRig(tuple(names[i] for i in order), np.array(positions)[order])


def frame_polyline(rig: HeadRig, step_mm: float = 0.75) -> np.ndarray:
    """Points along the glasses frame (two rims through the LEDs, the bridge), head frame, shape (n, 3).

    Each rim is an ellipse through its side's upper and lower LED, in the plane the LEDs span; a rig whose
    LED names are not ``upper_/lower_ L/R`` gets only the segments between consecutive LEDs.
    """
    where = dict(zip(rig.names, rig.positions))
    if not all(f"{a}_{s}" in where for a in ("upper", "lower") for s in ("L", "R")):
        loop = np.concatenate([rig.positions, rig.positions[:1]])
        return _resample(loop, step_mm)
    rims = []
    for side in ("L", "R"):
        upper, lower = where[f"upper_{side}"], where[f"lower_{side}"]
        centre = 0.5 * (upper + lower)
        half_x, half_y = abs(upper[0] - lower[0]) / 2 + 2.0, abs(upper[1] - lower[1]) / 2 + 2.0
        angle = np.linspace(0, 2 * np.pi, 97)
        cos, sin = np.cos(angle), np.sin(angle)
        x = centre[0] + half_x * np.sign(cos) * np.sqrt(np.abs(cos))  # a rounded rectangle (superellipse)
        y = centre[1] + half_y * np.sign(sin) * np.sqrt(np.abs(sin))
        # the rim tilts back towards the temple: depth linear in x through both LEDs
        z = upper[2] + (x - upper[0]) / (lower[0] - upper[0]) * (lower[2] - upper[2])
        rim = np.stack([x, y, z], axis=1)
        rims.append(_resample(rim, step_mm))
    bridge = np.array([[where["lower_L"][0] - 2, where["lower_L"][1] + 14, where["lower_L"][2]],
                       [where["lower_R"][0] + 2, where["lower_R"][1] + 14, where["lower_R"][2]]])
    return np.concatenate(rims + [_resample(bridge, step_mm)])


def _resample(polyline: np.ndarray, step_mm: float) -> np.ndarray:
    """Points every ``step_mm`` along a polyline ``(k, 3)``."""
    lengths = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    total = np.concatenate([[0.0], np.cumsum(lengths)])
    where = np.arange(0.0, total[-1] + 1e-9, step_mm)
    return np.stack([np.interp(where, total, polyline[:, d]) for d in range(3)], axis=1)

"""``calibration.toml``: aniposelib-compatible camera tables plus a metadata table.

Format
------
One table per camera, ``[cam_0]``, ``[cam_1]``, ... (in camera order), each with
``name`` (str), ``size`` ([width, height] px), ``matrix`` (3x3), ``distortions``
(OpenCV ``k1 k2 p1 p2 k3``; four ``k1..k4`` when ``fisheye = true``),
``rotation`` (Rodrigues vector of world2cam) and ``translation`` (world2cam, mm).
``[metadata]`` holds the board spec, date, livebridge version, world-frame
description and per-camera ``rms_px`` / ``views_used`` tables. Files written
by aniposelib (``CameraGroup.dump``) load as they are.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from livebridge.calibration.cameras import Camera, CameraGroup
from livebridge.errors import InputError
from livebridge.tomlio import load_toml, require, save_toml


def save_calibration(path: str | Path, group: CameraGroup, metadata: dict[str, Any] | None = None) -> None:
    """Write ``group`` (and ``metadata``) to a TOML file, atomically."""
    data: dict[str, Any] = {}
    for i, camera in enumerate(group.cameras):
        table = {
            "name": camera.name,
            "size": [int(camera.size[0]), int(camera.size[1])],
            "matrix": [[float(v) for v in row] for row in camera.matrix],
            "distortions": [float(v) for v in camera.distortions],
            "rotation": [float(v) for v in camera.rotation],
            "translation": [float(v) for v in camera.translation],
        }
        if camera.fisheye:
            table["fisheye"] = True
        data[f"cam_{i}"] = table
    if metadata:
        data["metadata"] = _plain(metadata)
    save_toml(path, data)


def load_calibration(path: str | Path) -> CameraGroup:
    """Read a ``calibration.toml`` (ours or aniposelib's); bad content raises :class:`InputError` naming the field."""
    data = load_toml(path)
    keys = [key for key in data if key != "metadata"]
    bad = [key for key in keys if not re.fullmatch(r"cam_\d+", key) or not isinstance(data[key], dict)]
    if bad:
        raise InputError("expected only [cam_N] tables and [metadata]", path, bad[0])
    if not keys:
        raise InputError("no [cam_N] tables", path)
    keys.sort(key=lambda key: int(key[4:]))
    cameras = [_camera(data[key], path, key) for key in keys]
    names = [c.name for c in cameras]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise InputError(f"camera name {name!r} is used twice", path, f"{keys[i]}.name")
    return CameraGroup(cameras)


def load_metadata(path: str | Path) -> dict[str, Any]:
    """The ``[metadata]`` table of a calibration file (empty when absent)."""
    metadata = load_toml(path).get("metadata", {})
    if not isinstance(metadata, dict):
        raise InputError("must be a table", path, "metadata")
    for key, kind in _METADATA_KINDS.items():
        if key in metadata:
            _check_metadata(metadata[key], kind, path, f"metadata.{key}")
    return metadata


# The metadata livebridge itself reads back (other keys are free-form notes): a per-camera table of numbers.
_METADATA_KINDS = {"rms_px": float, "rms_all_px": float, "views_used": int, "outliers": int, "world_frame": str}


def _check_metadata(value, kind: type, path, field: str) -> None:
    if kind is str:
        if not isinstance(value, str):
            raise InputError(f"expected text, got {value!r}", path, field)
        return
    if not isinstance(value, dict):
        raise InputError(f"expected a table of camera name = number, got {value!r}", path, field)
    kinds = (int, float) if kind is float else (int,)
    for name, number in value.items():
        if isinstance(number, bool) or not isinstance(number, kinds) or not np.isfinite(number) or number < 0:
            raise InputError(f"expected a finite number >= 0, got {number!r}", path, f"{field}.{name}")


_CAMERA_KEYS = ("name", "size", "matrix", "distortions", "rotation", "translation", "fisheye")
MAX_ROTATION_RAD = 2 * np.pi  # a Rodrigues vector's length is its angle; OpenCV writes at most pi


def _camera(table: dict[str, Any], path, key: str) -> Camera:
    unknown = sorted(set(table) - set(_CAMERA_KEYS))
    if unknown:
        raise InputError(f"unknown key {unknown[0]!r}; a camera table has {', '.join(_CAMERA_KEYS)}", path,
                         f"{key}.{unknown[0]}")
    name = require(table, "name", (str, int), path, key)
    fisheye = table.get("fisheye", False)
    if not isinstance(fisheye, bool):
        raise InputError(f"expected true or false, got {fisheye!r}", path, f"{key}.fisheye")
    size = _array(table, "size", path, key, (2,))
    if (size <= 0).any() or (size != np.round(size)).any():
        raise InputError(f"expected two positive whole numbers, got {table['size']!r}", path, f"{key}.size")
    matrix = _array(table, "matrix", path, key, (3, 3))
    if matrix[0, 0] <= 0 or matrix[1, 1] <= 0 or not np.allclose(matrix[2], [0, 0, 1]):
        raise InputError("expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with positive fx, fy", path,
                         f"{key}.matrix")
    distortions = _array(table, "distortions", path, key, None)
    expected = 4 if fisheye else 5
    if distortions.ndim != 1 or not 1 <= len(distortions) <= (4 if fisheye else 8):
        raise InputError(f"expected a list of {expected} numbers, got {table['distortions']!r}", path,
                         f"{key}.distortions")
    if len(distortions) > 5:
        if (distortions[5:] != 0).any():
            raise InputError("rational / thin-prism distortion terms (more than 5) are not supported", path,
                             f"{key}.distortions")
        distortions = distortions[:5]
    distortions = np.r_[distortions, np.zeros(expected - len(distortions))]
    rotation = _array(table, "rotation", path, key, (3,))
    if not np.all(np.abs(rotation) <= MAX_ROTATION_RAD) or np.linalg.norm(rotation) > MAX_ROTATION_RAD:
        raise InputError(f"a Rodrigues vector of at most 2 pi rad (one turn), got {table['rotation']!r}", path,
                         f"{key}.rotation")
    translation = _array(table, "translation", path, key, (3,))
    return Camera(str(name), (int(size[0]), int(size[1])), matrix, distortions, rotation, translation, fisheye)


def _array(table, field: str, path, key: str, shape: tuple[int, ...] | None) -> np.ndarray:
    value = require(table, field, list, path, key)
    try:
        if not _all_numbers(value):
            raise ValueError
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):  # text ("640" would convert), booleans, ragged rows
        raise InputError(f"expected numbers, got {value!r}", path, f"{key}.{field}") from None
    if shape is not None and array.shape != shape:
        want = "x".join(map(str, shape))
        raise InputError(f"expected shape {want}, got {array.shape} ({value!r})", path, f"{key}.{field}")
    if not np.isfinite(array).all():
        raise InputError("contains NaN or infinity", path, f"{key}.{field}")
    return array


def _all_numbers(value: Any) -> bool:
    """True when every leaf of nested lists is an int or a float (not a bool, not text)."""
    if isinstance(value, list):
        return all(_all_numbers(v) for v in value)
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _plain(value: Any) -> Any:
    """numpy scalars/arrays -> TOML-writable Python values."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value

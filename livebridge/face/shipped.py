"""Marker sets shipped with livebridge, by name (:data:`livebridge.face.SHIPPED_MARKER_SETS`).

``builtin`` and ``builtin-68`` are made from the built-in face in code (:mod:`livebridge.face.builtin`);
the others are marker-set files in ``livebridge/face/data`` (``ict-68`` -> ``ict_68.toml``).
"""

from __future__ import annotations

from pathlib import Path

from livebridge.errors import InputError
from livebridge.face import SHIPPED_MARKER_SETS
from livebridge.face.markers import MarkerSet

DATA = Path(__file__).parent / "data"


def shipped_marker_set(name: str) -> MarkerSet:
    """A marker set shipped with livebridge, by name (see :data:`SHIPPED_MARKER_SETS`)."""
    if name == "builtin":
        from livebridge.face.builtin import builtin_markers

        return builtin_markers()
    if name == "builtin-68":
        from livebridge.face.builtin import builtin_landmarks

        return builtin_landmarks()
    if name in SHIPPED_MARKER_SETS:
        return MarkerSet.load(DATA / f"{name.replace('-', '_')}.toml")
    raise InputError(f"no shipped marker set {name!r} (shipped: {', '.join(SHIPPED_MARKER_SETS)})")


def load_marker_set(spec: str | Path) -> MarkerSet:
    """A marker set by shipped name (:data:`SHIPPED_MARKER_SETS`) or from a marker-set TOML file."""
    if isinstance(spec, str) and spec in SHIPPED_MARKER_SETS:
        return shipped_marker_set(spec)
    return MarkerSet.load(spec)

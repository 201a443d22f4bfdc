"""Muscle and wrinkle control points (Erdoğdu §5.5.1-5.5.2): defined once on a reference face, carried to any face.

A control point set is a list of named points on a reference face (the built-in face by default, with its
22 thesis landmarks ``builtin-22``), each in a group (an action unit ``au12`` or a muscle
``zygomatic_major_L``), of a kind (``muscle`` or ``wrinkle``), in a face region (``upper``/``lower``, the
regions the thesis warps apart) and on a side (``L``, ``R`` or ``C`` for the midline). The groups carry a
recipe: which muscles of a Choe-Ko basis, contracted how far, make the action unit (so a basis can act as
the thesis's expressive source face). Sets are editable TOML files (``livebridge-control-points``):

.. code-block:: toml

    format = "livebridge-control-points"
    version = 1
    reference = "builtin-22"          # the landmark set (on the reference face) the positions go with

    [[group]]
    name = "au12"
    description = "AU12 lip corner puller"
    muscles = { zygomatic_major_L = 1.0, zygomatic_major_R = 1.0 }

    [[point]]
    name = "au12_corner_L"
    group = "au12"
    kind = "muscle"
    region = "lower"
    side = "L"
    position = [24.0, -40.0, 88.1]    # mm, on the reference face

A set is carried to another face by the landmark spline from the reference face's landmarks to that face's
landmarks, followed by snapping to the nearest surface point (:func:`carry_control_points`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.retarget.landmarks import LandmarkSet, surface_values
from livebridge.retarget.tps import Kernel, fit_tps
from livebridge.tomlio import load_toml, save_toml

FORMAT = "livebridge-control-points"
VERSION = 1
KINDS = ("muscle", "wrinkle")
REGIONS = ("upper", "lower")
SIDES = ("L", "R", "C")
DATA = Path(__file__).parent / "data"
SHIPPED_CONTROL_POINTS = ("thesis",)
"""Shipped sets: ``thesis``, on the built-in face: the thesis's AUs 1, 2, 4, 12, 14, 15, 17, 20 and every
muscle of the 16-element Choe-Ko basis."""
THESIS_AUS = (1, 2, 4, 12, 14, 15, 17, 20)


@dataclass(frozen=True)
class ControlGroup:
    """An action unit or a muscle: a name, what it does, and the basis contractions that make it."""

    name: str
    description: str = ""
    muscles: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class ControlPointSet:
    """Named control points on a reference face (see the module docstring).

    Attributes
    ----------
    names : tuple of str, length n
    groups : tuple of str, length n
        The group of each point.
    kinds, regions, sides : tuple of str, length n
    positions : ndarray, shape (n, 3)
        On the reference face, mm.
    reference : str
        The landmark set the positions go with (a shipped name or a file path).
    recipes : dict of str to ControlGroup
        By group name.
    """

    names: tuple[str, ...]
    groups: tuple[str, ...]
    kinds: tuple[str, ...]
    regions: tuple[str, ...]
    sides: tuple[str, ...]
    positions: np.ndarray
    reference: str = "builtin-22"
    recipes: dict[str, ControlGroup] = field(default_factory=dict)

    def __post_init__(self):
        positions = np.array(self.positions, dtype=np.float64).reshape(-1, 3)
        positions.setflags(write=False)
        object.__setattr__(self, "positions", positions)
        n = len(self.names)
        for what in ("groups", "kinds", "regions", "sides"):
            if len(getattr(self, what)) != n:
                raise InputError(f"{len(getattr(self, what))} {what} for {n} control points", field=what)
        if len(positions) != n:
            raise InputError(f"{len(positions)} positions for {n} control points", field="position")

    def __len__(self) -> int:
        return len(self.names)

    @property
    def group_names(self) -> tuple[str, ...]:
        """The groups in file order, each once."""
        return tuple(dict.fromkeys(self.groups))

    def select(self, groups=None, region: str | None = None, sides=None) -> np.ndarray:
        """Boolean mask (n,) of the points in ``groups`` (any when None), ``region`` and ``sides``."""
        mask = np.ones(len(self), dtype=bool)
        if groups is not None:
            wanted = set(groups)
            unknown = wanted - set(self.groups)
            if unknown:
                raise InputError(f"no control points for {', '.join(sorted(unknown))} (groups: "
                                 f"{', '.join(self.group_names)})", field="group")
            mask &= np.array([g in wanted for g in self.groups])
        if region is not None:
            mask &= np.array([r == region for r in self.regions])
        if sides is not None:
            mask &= np.array([s in sides for s in self.sides])
        return mask

    def subset(self, mask: np.ndarray) -> ControlPointSet:
        index = np.flatnonzero(mask)

        def pick(values):
            return tuple(values[i] for i in index)

        groups = pick(self.groups)
        return ControlPointSet(pick(self.names), groups, pick(self.kinds), pick(self.regions), pick(self.sides),
                               self.positions[index], self.reference,
                               {g: r for g, r in self.recipes.items() if g in groups})

    def on(self, vertices: np.ndarray, triangles: np.ndarray, landmarks: LandmarkSet,
           kernel: Kernel | str = Kernel.BIHARMONIC) -> np.ndarray:
        """The points carried from the reference face onto a face, shape (n, 3) (:func:`carry_control_points`)."""
        reference_mesh, reference_landmarks = reference_face(self.reference)
        return carry_control_points(self.positions, reference_mesh, reference_landmarks, (vertices, triangles),
                                    landmarks, kernel)

    # ------------------------------------------------------------------------------------------- files
    def to_toml(self) -> dict:
        groups = [{"name": g.name, "description": g.description, "muscles": dict(g.muscles)}
                  for g in self.recipes.values()]
        points = [{"name": n, "group": g, "kind": k, "region": r, "side": s,
                   "position": [round(float(v), 4) for v in p]}
                  for n, g, k, r, s, p in zip(self.names, self.groups, self.kinds, self.regions, self.sides,
                                              self.positions)]
        return {"format": FORMAT, "version": VERSION, "reference": self.reference, "group": groups, "point": points}

    def save(self, path: str | Path) -> None:
        save_toml(path, self.to_toml())

    @classmethod
    def load(cls, path: str | Path) -> ControlPointSet:
        """A control point set from its TOML file; every fault names the file and the point or group."""
        data = load_toml(path)
        if data.get("format") != FORMAT:
            raise InputError(f"not a control-point file (format = {data.get('format')!r}, expected {FORMAT!r})",
                             path, "format")
        if data.get("version") != VERSION:
            raise InputError(f"unsupported version {data.get('version')!r} (this livebridge reads {VERSION})",
                             path, "version")
        reference = data.get("reference", "builtin-22")
        if not isinstance(reference, str):
            raise InputError(f"expected a landmark set name or file, got {reference!r}", path, "reference")
        recipes = {}
        for k, row in enumerate(data.get("group", [])):
            name = row.get("name") if isinstance(row, dict) else None
            if not isinstance(name, str) or not name:
                raise InputError("a group needs a name", path, f"group {k}")
            muscles = row.get("muscles", {})
            if not isinstance(muscles, dict) or not all(_is_number(v) for v in muscles.values()):
                raise InputError("muscles must map muscle names to numbers", path, f"group {name}")
            recipes[name] = ControlGroup(name, str(row.get("description", "")),
                                         {m: float(v) for m, v in muscles.items()})
        rows = data.get("point", [])
        if not rows:
            raise InputError("no control points ([[point]] tables)", path, "point")
        columns = {key: [] for key in ("names", "groups", "kinds", "regions", "sides", "positions")}
        seen = set()
        for k, row in enumerate(rows):
            columns_row = _point_row(row, k, path)
            if columns_row[0] in seen:
                raise InputError("control point named twice", path, columns_row[0])
            seen.add(columns_row[0])
            for key, value in zip(columns, columns_row):
                columns[key].append(value)
        return cls(**{key: tuple(v) if key != "positions" else np.array(v) for key, v in columns.items()},
                   reference=reference, recipes=recipes)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and bool(np.isfinite(value))


def _point_row(row, k: int, path) -> tuple:
    if not isinstance(row, dict):
        raise InputError("a [[point]] must be a table", path, f"point {k}")
    name = row.get("name")
    if not isinstance(name, str) or not name:
        raise InputError("a control point needs a name", path, f"point {k}")
    for key, allowed in (("kind", KINDS), ("region", REGIONS), ("side", SIDES)):
        if row.get(key) not in allowed:
            raise InputError(f"{key} must be one of {', '.join(allowed)}, got {row.get(key)!r}", path, name)
    group = row.get("group")
    if not isinstance(group, str) or not group:
        raise InputError("a control point needs a group (an AU like 'au12' or a muscle name)", path, name)
    position = row.get("position")
    try:
        xyz = np.array(position, dtype=np.float64)
    except (TypeError, ValueError):
        xyz = np.array([])
    if xyz.shape != (3,) or not np.isfinite(xyz).all():
        raise InputError(f"position must be 3 finite numbers (mm), got {position!r}", path, name)
    return name, group, row["kind"], row["region"], row["side"], xyz


def load_control_points(spec: str | Path = "thesis") -> ControlPointSet:
    """A control point set by shipped name (:data:`SHIPPED_CONTROL_POINTS`) or from its TOML file."""
    if isinstance(spec, str) and spec in SHIPPED_CONTROL_POINTS:
        return ControlPointSet.load(DATA / f"control_points_{spec}.toml")
    return ControlPointSet.load(spec)


def reference_face(reference: str):
    """((vertices, triangles), landmarks) of a control point set's reference face.

    ``builtin-22`` / ``builtin-68``: the built-in face; ``ict-22`` / ``ict-68`` need the ICT face region, which
    livebridge does not ship: carry such sets with :func:`carry_control_points` and the mesh in hand.
    """
    from livebridge.retarget.landmarks import load_landmark_set

    if reference.startswith("builtin"):
        from livebridge.face.builtin import builtin_basis

        basis = builtin_basis()
        return (basis.neutral, basis.triangles), load_landmark_set(reference)
    raise InputError(f"no reference face for {reference!r}: control points defined on another face are carried "
                     "with carry_control_points and that face's mesh", field="reference")


def carry_control_points(control_points, source_mesh, source_landmarks: LandmarkSet, target_mesh,
                         target_landmarks: LandmarkSet, kernel: Kernel | str = Kernel.BIHARMONIC) -> np.ndarray:
    """Control points on a source face carried onto a target face (thesis §5.5.3 and §5.6.1), shape (n, 3).

    The landmark spline ``f`` (source landmarks -> target landmarks, matched by name; eq. 5.7) carries each
    point, which is then snapped to the nearest point of the target surface.

    Parameters
    ----------
    control_points : ControlPointSet or ndarray, shape (n, 3)
        Points on the source face (a set's ``positions``).
    source_mesh, target_mesh : (vertices (m, 3), triangles (t, 3))
    source_landmarks, target_landmarks : LandmarkSet
        Every landmark of the source set must be in the target set.
    kernel : Kernel or str

    Returns
    -------
    ndarray, shape (n, 3)
        On the target surface, mm.
    """
    from livebridge.retarget.basis import landmark_pairs

    points = control_points.positions if isinstance(control_points, ControlPointSet) else control_points
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    source_points, target_points = landmark_pairs(source_landmarks, source_mesh, target_landmarks, target_mesh)
    carried = fit_tps(source_points, target_points, kernel)(points)
    vertices, triangles = target_mesh
    return surface_values(carried, vertices, triangles, np.asarray(vertices, dtype=np.float64))

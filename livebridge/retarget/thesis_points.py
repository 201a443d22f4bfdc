"""How the shipped control points (``control_points_thesis.toml``) are made on the built-in face.

Action units (thesis Figure 5-7/5-8): points at fixed offsets (mm, in the face's x-y plane, mirrored for the
right side) from the thesis landmarks, projected onto the face along z. Muscles: for each element of the
built-in basis, up to :data:`POINTS_PER_MUSCLE` vertices spread over where that element moves at least half
its most. ``python -m livebridge.retarget.thesis_points OUT.toml`` rewrites the file; edit the file, not this,
to tune a face's points.
"""

from __future__ import annotations

import sys

import numpy as np

from livebridge.retarget.control_points import ControlGroup, ControlPointSet
from livebridge.retarget.landmarks import load_landmark_set, surface_values

POINTS_PER_MUSCLE = 4
# (AU, description, region, recipe, points: (name, kind, landmark, dx, dy, on both sides?))
AUS = (
    (1, "inner brow raiser (frontalis, pars medialis)", "upper", {"frontalis_L": 1.0, "frontalis_R": 1.0},
     (("brow", "muscle", "brow_inner", 0, 6), ("forehead", "muscle", "brow_inner", 2, 16),
      ("forehead_line", "wrinkle", "brow_inner", -4, 26))),
    (2, "outer brow raiser (frontalis, pars lateralis)", "upper", {"frontalis_L": 1.0, "frontalis_R": 1.0},
     (("brow_outer", "muscle", "brow_outer", -2, 6), ("brow_middle", "muscle", "brow_middle", 4, 8),
      ("forehead_line", "wrinkle", "brow_middle", 0, 22))),
    (4, "brow lowerer (corrugator supercilii, depressor supercilii)", "upper",
     {"corrugator_L": 1.0, "corrugator_R": 1.0},
     (("brow_inner", "muscle", "brow_inner", 0, 2), ("brow_middle", "muscle", "brow_middle", -6, 0),
      ("glabella", "wrinkle", "brow_inner", -9, -2))),
    (12, "lip corner puller (zygomatic major)", "lower", {"zygomatic_major_L": 1.0, "zygomatic_major_R": 1.0},
     (("corner", "muscle", "mouth_corner", 0, 0), ("cheek", "muscle", "mouth_corner", 10, 12),
      ("nasolabial", "wrinkle", "mouth_corner", 4, 14))),
    (14, "dimpler (buccinator); stand-in recipe: the Choe-Ko basis has no buccinator, risorius 0.6 with lips "
         "pressor 0.4 pulls the corners back and in", "lower",
     {"risorius_L": 0.6, "risorius_R": 0.6, "lips_pressor": 0.4},
     (("corner", "muscle", "mouth_corner", 4, 0), ("dimple", "wrinkle", "mouth_corner", 10, -4))),
    (15, "lip corner depressor (triangularis)", "lower", {"depressor_anguli_oris": 1.0},
     (("corner", "muscle", "mouth_corner", 0, -4), ("below", "muscle", "mouth_corner", 2, -16))),
    (17, "chin raiser (mentalis); stand-in recipe: the Choe-Ko basis has no mentalis, the lips pressor pushes the "
         "lower lip and chin up", "lower", {"lips_pressor": 1.0},
     (("chin_side", "muscle", "chin", 10, 8), ("lip_lower", "muscle", "lip_lower_outer", 8, 0))),
    (20, "lip stretcher (risorius)", "lower", {"risorius_L": 1.0, "risorius_R": 1.0},
     (("corner", "muscle", "mouth_corner", 0, 0), ("lateral", "muscle", "mouth_corner", 8, -2))),
)
# midline points (x = 0): (name, kind, landmark, dy)
MIDLINE_AUS = {17: (("chin", "muscle", "chin", 12), ("mentolabial", "wrinkle", "lip_lower_outer", -8)),
               4: (("glabella_centre", "wrinkle", "brow_inner_L", -1),)}


def _on_face(xy: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Points (n, 3) of the face's front at face coordinates ``xy (n, 2)``."""
    front = np.flatnonzero(normals[:, 2] > 0.3)
    nearest = front[np.argmin(np.linalg.norm(vertices[front, None, :2] - xy[None], axis=2), axis=0)]
    guess = np.column_stack([xy, vertices[nearest, 2]])
    return surface_values(guess, vertices, triangles, vertices)


def thesis_control_points() -> ControlPointSet:
    """The shipped set, computed on the built-in face."""
    from livebridge.face.builtin import builtin_basis
    from livebridge.face.meshio import vertex_normals

    basis = builtin_basis()
    vertices, triangles = basis.neutral, basis.triangles
    normals = vertex_normals(vertices, triangles)
    landmarks = load_landmark_set("builtin-22").as_dict(vertices, triangles)
    rows, recipes = [], {}
    for number, description, region, recipe, points in AUS:
        group = f"au{number}"
        recipes[group] = ControlGroup(group, f"AU{number} {description}", recipe)
        for name, kind, landmark, dx, dy in points:
            for side, sign in (("L", 1.0), ("R", -1.0)):
                at = landmarks[f"{landmark}_{side}"] if f"{landmark}_{side}" in landmarks else landmarks[landmark]
                xy = np.array([[at[0] + sign * dx, at[1] + dy]])
                rows.append((f"{group}_{name}_{side}", group, kind, region, side, xy))
        for name, kind, landmark, dy in MIDLINE_AUS.get(number, ()):
            rows.append((f"{group}_{name}", group, kind, region, "C", np.array([[0.0, landmarks[landmark][1] + dy]])))
    names, groups, kinds, regions, sides, positions = [], [], [], [], [], []
    for name, group, kind, region, side, xy in rows:
        names.append(name), groups.append(group), kinds.append(kind), regions.append(region), sides.append(side)
        positions.append(_on_face(xy, vertices, triangles, normals)[0])
    size = np.linalg.norm(basis.elements, axis=2)
    for k, muscle in enumerate(basis.muscles):
        recipes[muscle.name] = ControlGroup(muscle.name, muscle.description, {muscle.name: 1.0})
        strong = np.flatnonzero((size[k] >= 0.5 * size[k].max()) & (normals[:, 2] > 0.0))
        chosen = [strong[np.argmax(size[k, strong])]]
        distance = np.linalg.norm(vertices[strong] - vertices[chosen[0]], axis=1)
        while len(chosen) < POINTS_PER_MUSCLE and distance.max() > 4.0:
            chosen.append(strong[int(np.argmax(distance))])
            distance = np.minimum(distance, np.linalg.norm(vertices[strong] - vertices[chosen[-1]], axis=1))
        for j, vertex in enumerate(chosen):
            names.append(f"{muscle.name}_{j}"), groups.append(muscle.name), kinds.append("muscle")
            regions.append(muscle.region), sides.append(muscle.side or "C"), positions.append(vertices[vertex])
    return ControlPointSet(tuple(names), tuple(groups), tuple(kinds), tuple(regions), tuple(sides),
                           np.array(positions), "builtin-22", recipes)


HEADER = """\
# Muscle and wrinkle control points (Erdogdu's thesis, section 5.5) on the built-in face, in mm, with the
# landmark set they were placed against (`reference`). Written by `python -m livebridge.retarget.thesis_points
# OUT.toml`; edit a copy by hand and pass it with `livebridge retarget au --control-points my_points.toml`.
#
# How to edit:
# - [[group]]: one action unit (au1 ... au20) or one Choe-Ko muscle. `muscles` is its recipe: which elements of
#   the source basis, contracted how far (0-1), make the expressive source face the control points are read on.
#   AU14 and AU17 are STAND-IN recipes: the 16-muscle basis has no buccinator and no mentalis, so AU14 uses
#   risorius + lips pressor and AU17 the lips pressor. Give your own recipe if your basis has those muscles.
# - [[point]]: name (unique), group (a group's name), kind (muscle | wrinkle), region (upper | lower: which
#   per-region spline moves it), side (L | R | C: --side left/right keeps only that side's points), position
#   (x, y, z on the reference face: x to the face's left, y up, z out of the face). A point off the surface is
#   snapped to the nearest surface point when carried to a face.
"""

if __name__ == "__main__":
    from pathlib import Path

    out = Path(sys.argv[1])
    thesis_control_points().save(out)
    out.write_text(HEADER + "\n" + out.read_text())

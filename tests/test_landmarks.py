"""Landmark sets: the shipped thesis-22 sets against the generator and ICT-FaceKit, closest surface points against
brute force, and ``livebridge landmarks place`` / ``show`` round trips."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from factories import assert_cli_refused

from livebridge.cli import main
from livebridge.errors import InputError
from livebridge.face import builtin
from livebridge.face.builtin import builtin_basis, builtin_landmarks
from livebridge.face.markers import landmark_name
from livebridge.face.shipped import shipped_marker_set
from livebridge.retarget.au import save_mesh
from livebridge.retarget.landmarks import (
    MIRROR_PAIRS,
    SADDLE,
    THESIS_22,
    THESIS_22_NAMES,
    LandmarkSet,
    _closest_on_triangles,
    closest_surface_points,
    load_landmark_set,
    thesis_22_from_68,
    thesis_points_from_68,
)


@pytest.fixture(scope="module")
def face():
    return builtin_basis()


def _at(names, positions, name):
    return positions[names.index(name)]


def test_shipped_sets_load_with_the_22_names_in_thesis_order(face):
    for spec in ("builtin-22", "ict-22"):
        landmarks = load_landmark_set(spec)
        assert isinstance(landmarks, LandmarkSet)
        assert landmarks.names == THESIS_22_NAMES and len(landmarks) == 22
        landmarks.require_thesis_22()
    load_landmark_set("builtin-22").checked_on(len(face.triangles))


def test_builtin_22_file_is_what_the_derivation_gives_today(face):
    """The shipped file is not stale: deriving the 22 from builtin-68 again gives the same surface points."""
    derived = thesis_22_from_68(builtin_landmarks(), face.neutral, face.triangles)
    shipped = load_landmark_set("builtin-22")
    np.testing.assert_allclose(shipped.positions(face.neutral, face.triangles),
                               derived.positions(face.neutral, face.triangles), atol=1e-9)
    assert shipped.regions == derived.regions and shipped.roles == derived.roles


def test_builtin_22_sit_where_the_generator_puts_the_features(face):
    landmarks = load_landmark_set("builtin-22")
    names, at = landmarks.names, landmarks.positions(face.neutral, face.triangles)
    surface = builtin._surface
    for side, sign in (("L", 1), ("R", -1)):  # the subject's left is +x
        for corner, lateral in (("outer", 1), ("inner", -1)):
            feature = surface(np.array(sign * (builtin.EYE_X + lateral * builtin.EYE_HALF_WIDTH)),
                              np.array(builtin.EYE_Y))
            # builtin-68 (which the 22 copy) puts the corners 1 mm inside where the lid margins meet
            assert np.linalg.norm(_at(names, at, f"eye_{corner}_{side}") - feature) < 2.0
        feature = surface(np.array(sign * builtin.MOUTH_HALF_WIDTH), np.array(builtin.MOUTH_Y))
        assert np.linalg.norm(_at(names, at, f"mouth_corner_{side}") - feature) < 0.5
    tip = face.neutral[np.argmax(face.neutral[:, 2])]  # the nose tip is the face's most forward point
    assert np.linalg.norm(_at(names, at, "nose_tip") - tip) < 1.5
    middle = [_at(names, at, name) for name in ("lip_upper_outer", "lip_upper_inner", "lip_lower_inner",
                                                "lip_lower_outer", "chin")]
    assert all(abs(point[0]) < 0.01 for point in middle)  # on the midline
    heights = [point[1] for point in middle]
    assert heights == sorted(heights, reverse=True)  # top to bottom
    assert abs(heights[1] - builtin.MOUTH_Y) < 1.5 and abs(heights[2] - builtin.MOUTH_Y) < 1.5
    assert abs(heights[4] - (builtin.MOUTH_Y - 31.0)) < 10.0  # within the generator's chin bump
    for side, sign in (("L", 1), ("R", -1)):  # the brows above the eyes, the saddles beside the nasal root
        assert _at(names, at, f"brow_middle_{side}")[1] > builtin.EYE_Y + builtin.EYE_UPPER
        saddle = _at(names, at, f"nose_saddle_{side}")
        assert 0 < sign * saddle[0] < sign * _at(names, at, f"eye_inner_{side}")[0]


@pytest.mark.parametrize("spec", ["builtin-22", "ict-22"])
def test_left_and_right_are_mirror_images(spec, face, request):
    basis = face if spec == "builtin-22" else request.getfixturevalue("ict")
    landmarks = load_landmark_set(spec)
    at = landmarks.positions(basis.neutral, basis.triangles)
    gaps = [np.abs(_at(landmarks.names, at, left) * [-1, 1, 1] - _at(landmarks.names, at, right)).max()
            for left, right in MIRROR_PAIRS]
    assert len(MIRROR_PAIRS) == 8  # brows 3, eye corners 2, nose saddles, nose peaks, mouth corners
    if spec == "builtin-22":  # the generator mirrors exactly
        assert max(gaps) < 1e-6, gaps
    else:  # the kit's face is symmetric to a few micrometres too (measured: at most 0.005 mm)
        assert max(gaps) < 0.05, gaps
    for left, right in MIRROR_PAIRS:
        assert _at(landmarks.names, at, left)[0] > 0 > _at(landmarks.names, at, right)[0]


def test_ict_22_are_the_kits_landmark_vertices(ict, shared_data):
    kit = np.load(shared_data / "ict-facekit" / "face_region.npz")
    vertex_ids, neutral_mm = kit["landmark_vertices"], kit["neutral"].astype(np.float64) * 10.0
    np.testing.assert_allclose(ict.neutral, neutral_mm, atol=1e-3)  # the basis is the kit's face region, in mm
    landmarks = load_landmark_set("ict-22").checked_on(len(ict.triangles))
    at = landmarks.positions(ict.neutral, ict.triangles)
    for (name, source), point in zip(THESIS_22, at):
        if isinstance(source, tuple):  # a nose saddle: on the surface, between the bridge and the inner corner
            bridge, corner = neutral_mm[vertex_ids[28]], neutral_mm[vertex_ids[source[1]]]
            assert min(bridge[0], corner[0]) < point[0] < max(bridge[0], corner[0]), name
            assert closest_surface_points(point[None], ict.neutral, ict.triangles)[2][0] < 1e-6
        else:
            np.testing.assert_allclose(point, neutral_mm[vertex_ids[source]], atol=1e-3, err_msg=name)
    assert SADDLE in {s[0] for _, s in THESIS_22 if isinstance(s, tuple)}


def test_closest_surface_points_match_brute_force(face, rng):
    """Against every triangle of the mesh (Ericson's routine checked against dense sampling of triangles)."""
    points = face.neutral[rng.integers(0, len(face.neutral), 40)] + rng.normal(0, 3.0, (40, 3))
    triangle, barycentric, distance = closest_surface_points(points, face.neutral, face.triangles)
    corners = face.neutral[face.triangles]
    for p, d in zip(points, distance):
        best = _closest_on_triangles(np.tile(p, (len(corners), 1)), corners)
        assert abs(np.linalg.norm(np.einsum("nk,nkd->nd", best, corners) - p, axis=1).min() - d) < 1e-9
    np.testing.assert_allclose(barycentric.sum(axis=1), 1.0)
    for _ in range(5):
        tri, p = rng.normal(size=(1, 3, 3)), 2 * rng.normal(size=(1, 3))
        u = rng.random((200_000, 2))
        u[u.sum(1) > 1] = 1 - u[u.sum(1) > 1]
        samples = tri[0, 0] + u[:, :1] * (tri[0, 1] - tri[0, 0]) + u[:, 1:] * (tri[0, 2] - tri[0, 0])
        exact = np.linalg.norm(_closest_on_triangles(p, tri)[0] @ tri[0] - p[0])
        assert exact <= np.linalg.norm(samples - p, axis=1).min() + 1e-12
        assert np.linalg.norm(samples - p, axis=1).min() - exact < 0.02


def test_thesis_22_needs_a_68_point_set(face):
    from livebridge.errors import InputError

    with pytest.raises(InputError, match="lm_00"):
        thesis_22_from_68(builtin_landmarks().subset(np.arange(1, 68)), face.neutral, face.triangles)


def test_a_68_point_file_s_numbers_read_as_the_thesis_s_names(face):
    """What a landmark detector writes for a scan (``lm_00`` .. ``lm_67``) gives the thesis's 22 as the shipped
    derivation does, without the iBUG points they came from (one control point twice) or the jaw line (out of
    the face crop), and keeps the rest; names already there are left alone."""
    markers = builtin_landmarks()
    points = dict(zip(markers.names, markers.positions(face.neutral, face.triangles)))
    thesis = load_landmark_set("builtin-22").as_dict(face.neutral, face.triangles)
    named = thesis_points_from_68(points, face.neutral)
    for name, source in THESIS_22:
        if isinstance(source, int):
            np.testing.assert_array_equal(named[name], points[landmark_name(source)], err_msg=name)
            assert landmark_name(source) not in named
        else:  # the scan point nearest the midpoint, where the shipped set takes the nearest surface point
            assert np.linalg.norm(named[name] - thesis[name]) < 2.0, name
    assert not any(landmark_name(number) in named for number in range(17))
    assert all(landmark_name(number) in named for number in (28, 37, 38, 40, 41, 43, 44, 46, 47, 60, 64))
    assert len(named) == 22 + 68 - 17 - 20 + 1  # lm_08 (the chin) is both jaw line and a thesis point
    mixed = {**thesis, "lm_30": points["lm_30"] + 5.0}  # a nose tip of its own: lm_30 is another point then
    kept = thesis_points_from_68(mixed, face.neutral)
    assert kept.keys() == mixed.keys() and all(kept[name] is mixed[name] for name in mixed)
    from_one = {f"lm_{int(name[3:]) + 1:02d}": xyz for name, xyz in points.items()}  # an iBUG .pts count
    with pytest.raises(InputError, match="lm_68: the 68 iBUG points are numbered lm_00 ... lm_67") as refused:
        thesis_points_from_68(from_one, face.neutral, "scan.landmarks.csv")
    assert "scan.landmarks.csv" in str(refused.value)


def _run(*args):
    result = CliRunner().invoke(main, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result


def test_place_from_vertices_round_trips(tmp_path, face, rng):
    ids = {name: int(v) for name, v in zip(THESIS_22_NAMES, rng.choice(len(face.neutral), 22, replace=False))}
    (tmp_path / "ids.toml").write_text("".join(f"{name} = {v}\n" for name, v in ids.items()))
    _run("landmarks", "place", "builtin", "--vertices", tmp_path / "ids.toml", "--out", tmp_path / "lm.toml",
         "--require-22")
    placed = load_landmark_set(tmp_path / "lm.toml")
    assert placed.names == THESIS_22_NAMES
    np.testing.assert_array_equal(placed.positions(face.neutral, face.triangles), face.neutral[list(ids.values())])
    assert placed.regions[0] == "upper" and placed.regions[-1] == "lower"  # brows upper, chin lower


def test_place_from_points_round_trips_and_snaps(tmp_path, face):
    """Points on the surface come back exactly; points 1 mm off along the normal come back to within 2 mm (the
    nearest surface point is at most 1 mm from the point, so at most 2 mm from where it started) and mostly
    to where they started (a concave spot, the eye corners, has nearer surface than the normal's foot)."""
    from livebridge.face.meshio import vertex_normals

    truth = load_landmark_set("builtin-22")
    on_surface = truth.positions(face.neutral, face.triangles)
    normals = vertex_normals(face.neutral, face.triangles)[face.triangles[truth.triangles]]
    normal = np.einsum("nk,nkd->nd", truth.barycentric, normals)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    for name, points, tolerance in (("on", on_surface, 1e-9), ("off", on_surface + normal, 2.0)):
        rows = "".join(f"{n},{x!r},{y!r},{z!r}\n" for n, (x, y, z) in zip(truth.names, points.tolist()))
        (tmp_path / f"{name}.csv").write_text("name,x,y,z\n" + rows)
        _run("landmarks", "place", "builtin", "--points", tmp_path / f"{name}.csv", "--out",
             tmp_path / f"{name}.toml")
        placed = load_landmark_set(tmp_path / f"{name}.toml").positions(face.neutral, face.triangles)
        error = np.linalg.norm(placed - on_surface, axis=1)
        assert error.max() < tolerance, (name, error.max())
        assert np.median(error) < 0.1 * tolerance + 1e-9, (name, np.median(error))


def test_place_in_other_units_on_an_obj(tmp_path, face):
    """An OBJ in centimetres with points in centimetres: the same landmarks as on the mm basis."""
    lines = [f"v {x / 10!r} {y / 10!r} {z / 10!r}" for x, y, z in face.neutral.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in face.triangles.tolist()]
    (tmp_path / "face.obj").write_text("\n".join(lines) + "\n")
    truth = load_landmark_set("builtin-22")
    points = truth.positions(face.neutral, face.triangles) / 10
    (tmp_path / "p.csv").write_text("".join(f"{n},{x!r},{y!r},{z!r}\n" for n, (x, y, z) in zip(truth.names,
                                                                                         points.tolist())))
    _run("landmarks", "place", tmp_path / "face.obj", "--points", tmp_path / "p.csv", "--units", "cm",
         "--out", tmp_path / "lm.toml")
    placed = load_landmark_set(tmp_path / "lm.toml")
    np.testing.assert_allclose(placed.positions(face.neutral, face.triangles),
                               truth.positions(face.neutral, face.triangles), atol=1e-6)


def test_far_point_and_missing_landmark_name_the_file_and_landmark(tmp_path):
    (tmp_path / "p.csv").write_text("chin,0,-80,89.94\nnose_tip,0,-7,140\n")
    result = CliRunner().invoke(main, ["landmarks", "place", "builtin", "--points", str(tmp_path / "p.csv"),
                                       "--out", str(tmp_path / "lm.toml")])
    assert result.exit_code != 0
    assert "p.csv: nose_tip:" in result.output and "mm from the mesh surface" in result.output
    far = float(result.output.split("nose_tip: ")[1].split(" mm")[0])
    assert 15 < far < 25  # the tip is about 120 mm forward: this point is about 20 mm in front of it
    result = CliRunner().invoke(main, ["landmarks", "place", "builtin", "--points", str(tmp_path / "p.csv"),
                                       "--out", str(tmp_path / "lm.toml"), "--max-distance", "30", "--require-22"])
    assert result.exit_code != 0 and "p.csv" in result.output and "20 landmarks missing" in result.output
    assert "brow_outer_L" in result.output and not (tmp_path / "lm.toml").exists()


def test_show_renders_an_image(tmp_path):
    _run("landmarks", "show", "builtin", "builtin-22", "--out", tmp_path / "lm.png", "--dpi", "40")
    assert (tmp_path / "lm.png").read_bytes()[:4] == b"\x89PNG"


def test_builtin_68_names_are_what_the_derivation_reads():
    assert {landmark_name(i) for i in range(68)} <= set(shipped_marker_set("builtin-68").names)


def test_place_at_a_vertex_takes_a_triangle_with_area(tmp_path, face):
    """A zero-area triangle listed first at the vertex (an exporter's sliver) is passed over: a landmark on it
    would be refused as off the surface by every transfer."""
    vertex = int(face.triangles[100, 0])
    triangles = np.vstack([[[vertex, vertex, vertex]], face.triangles])
    save_mesh(tmp_path / "sliver.obj", face.neutral, triangles)
    (tmp_path / "ids.toml").write_text(f"nose_tip = {vertex}\n")
    _run("landmarks", "place", tmp_path / "sliver.obj", "--vertices", tmp_path / "ids.toml", "--out",
         tmp_path / "lm.toml")
    placed = LandmarkSet.load(tmp_path / "lm.toml")
    assert placed.triangles[0] != 0 and vertex in triangles[placed.triangles[0]]
    assert np.allclose(placed.positions(face.neutral, triangles), face.neutral[vertex])


@pytest.mark.parametrize("corners", [
    [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]],  # on a line: no area
    [[0.0, 0.0, 0.0], [1e-6, 0.0, 0.0], [0.0, 1e-6, 0.0]],  # 1e-13 of the median area (the OBJ's last digit)
], ids=["line", "sliver"])
def test_place_refuses_a_vertex_in_triangles_without_surface_only(tmp_path, face, corners):
    """Either is no surface to the transfers (``surface_triangles``): a landmark on a vertex in such triangles
    only is refused at once, not by every transfer later."""
    n = len(face.neutral)
    triangles = np.vstack([face.triangles, [[n, n + 1, n + 2]]])
    save_mesh(tmp_path / "mesh.obj", np.vstack([face.neutral, corners]), triangles)
    (tmp_path / "ids.toml").write_text(f"chin = {n + 1}\n")
    result = CliRunner().invoke(main, ["landmarks", "place", str(tmp_path / "mesh.obj"), "--vertices",
                                       str(tmp_path / "ids.toml"), "--out", str(tmp_path / "lm.toml")])
    assert_cli_refused(result, "ids.toml", "chin", f"vertex {n + 1}", "no area")


def test_place_at_points_passes_over_slivers_onto_the_surface(tmp_path, face):
    """A face written with a repeated corner and a zero-area triangle along a real edge, both through the landmark
    (as exporters and scanners leave them): the landmark lands on a triangle with area, where it was, and the
    transfer through it runs (it refuses a landmark on a sliver as off the surface)."""
    truth = load_landmark_set("builtin-22")
    on_surface = truth.positions(face.neutral, face.triangles)
    k = THESIS_22_NAMES.index("nose_tip")
    a, b, _ = face.triangles[truth.triangles[k]]
    n = len(face.neutral)
    # three new vertices on the line through the landmark along its triangle's edge ab: no area, at the landmark
    along = face.neutral[b] - face.neutral[a]
    line = on_surface[k] + np.outer([-1.0, 0.0, 1.0], along)
    vertices = np.vstack([face.neutral, line])
    triangles = np.vstack([[[n, n + 1, n + 2], [n + 1, n + 1, n]], face.triangles])
    save_mesh(tmp_path / "slivers.obj", vertices, triangles)
    rows = "".join(f"{name},{x!r},{y!r},{z!r}\n" for name, (x, y, z) in zip(truth.names, on_surface.tolist()))
    (tmp_path / "p.csv").write_text(rows)
    _run("landmarks", "place", tmp_path / "slivers.obj", "--points", tmp_path / "p.csv", "--out", tmp_path / "lm.toml")
    placed = load_landmark_set(tmp_path / "lm.toml")
    assert (placed.triangles >= 2).all()  # never one of the two slivers
    assert np.abs(placed.positions(vertices, triangles) - on_surface).max() < 1e-5  # the OBJ's digits
    _run("retarget", "basis", "--source", "builtin", "--source-landmarks", "builtin-22", "--target",
         tmp_path / "slivers.obj", "--target-landmarks", tmp_path / "lm.toml", "--out", tmp_path / "out.npz")


def test_a_vertex_thrown_far_off_the_mesh_is_refused_naming_it(tmp_path, face):
    """One vertex at 1e30 mm (a corrupt file) is named, not taken for face: before, the landmark on its triangle
    was called off the surface (the mean triangle area it was judged by was astronomical) or a triangulation
    failed inside the transfer."""
    vertices = face.neutral.copy()
    vertices[7] = [1e30, 0.0, 0.0]
    save_mesh(tmp_path / "far.obj", vertices, face.triangles)
    result = CliRunner().invoke(main, ["retarget", "basis", "--source", "builtin", "--source-landmarks",
                                       "builtin-22", "--target", str(tmp_path / "far.obj"), "--target-landmarks",
                                       "builtin-22", "--out", str(tmp_path / "out.npz")])
    assert_cli_refused(result, "far.obj", "vertex 7 lies 1e+30", "corrupt")


@pytest.mark.parametrize("row,words", [
    (",0,-80,89.94\n", ("p.csv", "line 1", "no name")),
    ("nose_tip,1e300,0,0\n", ("p.csv", "nose_tip", "1e+300 mm from the mesh surface")),
])
def test_place_refuses_an_unnamed_or_astronomically_far_point(tmp_path, row, words):
    (tmp_path / "p.csv").write_text(row)
    result = CliRunner().invoke(main, ["landmarks", "place", "builtin", "--points", str(tmp_path / "p.csv"),
                                       "--out", str(tmp_path / "lm.toml")])
    assert_cli_refused(result, *words)


@pytest.mark.parametrize("command", ["place", "show"])
def test_a_mesh_with_a_nan_vertex_is_refused_naming_the_file_and_vertex(tmp_path, face, command):
    vertices = face.neutral.copy()
    vertices[4] = np.nan
    save_mesh(tmp_path / "nan.obj", vertices, face.triangles)
    (tmp_path / "p.csv").write_text("chin,0,-80,89.94\n")
    args = (["place", str(tmp_path / "nan.obj"), "--points", str(tmp_path / "p.csv"), "--out",
             str(tmp_path / "lm.toml")] if command == "place" else
            ["show", str(tmp_path / "nan.obj"), "builtin-22", "--out", str(tmp_path / "lm.png")])
    assert_cli_refused(CliRunner().invoke(main, ["landmarks", *args]), "nan.obj", "vertex 5 is not finite")


@pytest.mark.parametrize("landmarks", ["placed", "builtin-22"])
def test_landmarks_of_one_mesh_are_refused_on_another_naming_the_file(tmp_path, face, landmarks):
    """A landmark file names triangles: on a mesh of other triangles (here the built-in face less one) they are
    other places, and a transfer through them came out 100-600 % off without a word. `landmarks place` writes
    the mesh's triangle count into the file, and builtin-22 carries it, so the other mesh is refused by name."""
    truth = load_landmark_set("builtin-22")
    rows = "".join(f"{n},{x!r},{y!r},{z!r}\n" for n, (x, y, z) in
                   zip(truth.names, truth.positions(face.neutral, face.triangles).tolist()))
    (tmp_path / "points.csv").write_text(rows)
    _run("landmarks", "place", "builtin", "--points", tmp_path / "points.csv", "--out", tmp_path / "placed.toml")
    assert load_landmark_set(tmp_path / "placed.toml").mesh_triangles == len(face.triangles)
    save_mesh(tmp_path / "other.obj", face.neutral, face.triangles[:-1])
    spec = str(tmp_path / "placed.toml") if landmarks == "placed" else landmarks
    result = CliRunner().invoke(main, ["landmarks", "show", str(tmp_path / "other.obj"), spec, "--out",
                                       str(tmp_path / "lm.png")])
    assert_cli_refused(result, "placed.toml" if landmarks == "placed" else "builtin-22",
                       f"made for a mesh of {len(face.triangles)} triangles")


def test_landmarks_move_off_a_small_hole_s_rim_but_not_off_an_opening():
    """On a flat 10 x 10 grid (1 mm) with one cell's two triangles missing, a landmark on the hole's rim moves to
    whole surface within one edge; an opening's landmark (a mouth corner) stays where it was placed."""
    from livebridge.retarget.checks import check_landmarks_on, moved_off_rims
    from livebridge.retarget.landmarks import place_at_points

    i, j = np.meshgrid(np.arange(11), np.arange(11), indexing="ij")
    vertices = np.column_stack([i.ravel(), j.ravel(), np.zeros(i.size)]).astype(float)
    index = np.arange(121).reshape(11, 11)
    triangles = [(index[a, b], index[a + 1, b], index[a + 1, b + 1]) for a in range(10) for b in range(10)]
    triangles += [(index[a, b], index[a + 1, b + 1], index[a, b + 1]) for a in range(10) for b in range(10)]
    triangles = np.array([t for t in triangles if not (5 in (t[0] // 11,) and 5 == t[0] % 11)])  # cell (5, 5) out
    assert len(triangles) == 198
    at = {"brow_middle_L": np.array([5.5, 4.9, 0.0]), "mouth_corner_L": np.array([5.3, 6.1, 0.0])}
    placed = place_at_points(at, vertices, triangles, 1.0)
    with pytest.raises(InputError, match="rim of a hole"):
        check_landmarks_on(placed, vertices, triangles, "lm.toml")
    moved = moved_off_rims(placed, vertices, triangles)
    positions = moved.positions(vertices, triangles)
    assert np.linalg.norm(positions[0] - at["brow_middle_L"]) <= 1.0  # within one edge
    np.testing.assert_array_equal(positions[1], placed.positions(vertices, triangles)[1])
    check_landmarks_on(moved, vertices, triangles, "lm.toml")

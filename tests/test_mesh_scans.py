"""Mesh scans are read by their surface, not their vertices: a mesh dense in places and sparse in others
resamples without holes, its leftover vertices are no surface, what the face's front hides (a modelled head's
teeth and eyeballs) is cut, and vertex colours are carried over the triangles."""

from __future__ import annotations

import numpy as np
import pytest

from livebridge.face.builtin import builtin_basis
from livebridge.retarget.face_scan import prepare_expression, prepare_neutral
from livebridge.retarget.landmarks import load_landmark_set
from livebridge.retarget.mesh_samples import surface_samples
from livebridge.retarget.scan import Scan, read_scan

GRID = (60, 60)


@pytest.fixture(scope="module")
def face():
    """(the built-in face's basis, its 22 landmarks as a dict)."""
    basis = builtin_basis()
    return basis, load_landmark_set("builtin-22").as_dict(basis.neutral, basis.triangles)


def _neutral(scan: Scan, landmarks: dict):
    return prepare_neutral(scan, landmarks, landmarks, shape=GRID)


def _split(vertices: np.ndarray, triangles: np.ndarray, chosen: np.ndarray, n: int):
    """The mesh with each ``chosen`` triangle split into n^2 (its own new vertices: cracks at the edges, as a
    scanner's decimated mesh has none, but the surface is the same)."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    bary = np.stack([1 - (i[keep] + j[keep]) / n, i[keep] / n, j[keep] / n], axis=1)  # (k, 3)
    index = -np.ones((n + 1, n + 1), int)
    index[keep] = np.arange(keep.sum())
    small = [(index[a, b], index[a + 1, b], index[a, b + 1]) for a in range(n) for b in range(n - a)]
    small += [(index[a + 1, b], index[a + 1, b + 1], index[a, b + 1]) for a in range(n) for b in range(n - a - 1)]
    small = np.array(small)
    new_vertices, new_triangles = [vertices], [triangles[~chosen]]
    count = len(vertices)
    for triangle in triangles[chosen]:
        new_vertices.append(bary @ vertices[triangle])
        new_triangles.append(small + count)
        count += len(bary)
    return np.vstack(new_vertices), np.vstack(new_triangles)


def test_a_mesh_dense_in_places_resamples_without_holes_where_it_is_sparse(face):
    """On the default grid (cells finer than the face's sparse vertices), as a scanner's decimated mesh is."""
    basis, landmarks = face

    def neutral(scan):
        return prepare_neutral(scan, landmarks, landmarks, mesh_spacing=1.0)

    uniform = neutral(Scan(basis.neutral, basis.triangles))
    near = np.linalg.norm(basis.neutral[basis.triangles].mean(axis=1) - landmarks["nose_tip"], axis=1) < 30
    vertices, triangles = _split(basis.neutral, basis.triangles, near, 6)  # the nose and around it 36 times denser
    assert len(vertices) > 2.5 * len(basis.neutral)
    leftovers = landmarks["nose_tip"] + np.random.default_rng(0).normal(0, 20, (500, 3))  # no triangle uses them
    adaptive = neutral(Scan(np.vstack([vertices, leftovers]), triangles))
    assert adaptive.grid.valid.sum() >= 0.995 * uniform.grid.valid.sum()  # from its vertices: 0.96 of it
    both = adaptive.grid.valid & uniform.grid.valid
    assert np.percentile(np.abs(adaptive.grid.heights[both] - uniform.grid.heights[both]), 99) < 0.05


def test_what_the_face_hides_is_cut_from_a_modelled_head(face):
    """Teeth behind the closed lips (the lower face's skin 4 mm further in) change no grid height, of the neutral
    nor of a smile. (Through an opened mouth they are seen, as a scanner sees them.)"""
    basis, landmarks = face
    mouth = 0.5 * (landmarks["mouth_corner_L"] + landmarks["mouth_corner_R"])
    inside = np.linalg.norm(basis.neutral[basis.triangles].mean(axis=1) - mouth, axis=1) < 25

    def head(vertices):
        teeth = vertices[basis.triangles[inside]].reshape(-1, 3) - [0.0, 0.0, 4.0]
        return Scan(np.vstack([vertices, teeth]),
                    np.vstack([basis.triangles, len(vertices) + np.arange(len(teeth)).reshape(-1, 3)]))

    neutral, modelled = _neutral(Scan(basis.neutral, basis.triangles), landmarks), _neutral(head(basis.neutral),
                                                                                          landmarks)
    assert np.array_equal(neutral.grid.valid, modelled.grid.valid)
    assert np.abs(modelled.grid.heights - neutral.grid.heights)[neutral.grid.valid].max() < 1e-9
    smile = basis.neutral + basis.elements[basis.index("zygomatic_major_L")]
    smile_landmarks = load_landmark_set("builtin-22").as_dict(smile, basis.triangles)
    skin = prepare_expression(Scan(smile, basis.triangles), smile_landmarks, neutral)
    with_teeth = prepare_expression(head(smile), smile_landmarks, neutral)
    assert np.array_equal(skin.grid.valid, with_teeth.grid.valid)
    assert np.abs(with_teeth.grid.heights - skin.grid.heights)[skin.grid.valid].max() < 1e-9


def test_vertex_colours_are_carried_over_the_triangles(face):
    basis, _ = face
    colours = (basis.neutral - basis.neutral.min(axis=0)) / np.ptp(basis.neutral, axis=0)  # linear in position
    points = Scan(basis.neutral, basis.triangles, colours).as_points(spacing=1.0)
    assert not points.is_mesh and len(points.points) > 2 * len(basis.neutral)
    expected = (points.points - basis.neutral.min(axis=0)) / np.ptp(basis.neutral, axis=0)
    assert np.abs(points.colours - expected).max() < 1e-9


def test_samples_cover_each_triangle_once_per_spacing_squared():
    corners = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [10.0, 10.0, 5.0]])
    triangles = np.array([[0, 1, 2], [1, 3, 2]])
    samples, owner, bary = surface_samples(corners, triangles, spacing=0.5)
    area = np.array([50.0, 0.5 * np.linalg.norm(np.cross(corners[3] - corners[1], corners[2] - corners[1]))])
    counts = np.bincount(owner, minlength=2)
    assert np.allclose(counts, np.ceil(np.sqrt(area) / 0.5) ** 2)
    assert np.allclose(samples, np.einsum("sk,skd->sd", bary, corners[triangles[owner]]))
    assert (bary > 0).all() and np.allclose(bary.sum(axis=1), 1.0)  # centroids: inside, never on an edge


def test_ict_full_head_obj_files_build_what_their_face_region_builds(tmp_path, shared_data):
    """ICT-FaceKit's OBJ files as a modelled head's scans (eyes, lashes, teeth, gums and the back of the head;
    their MTL is not shipped, so its line is dropped): the same grid and elements as the face region alone."""
    from livebridge.retarget.scans import basis_from_scans

    kit = np.load(shared_data / "ict-facekit" / "face_region.npz")
    names = list(kit["names"])
    landmark_set = load_landmark_set("ict-22")
    shapes = {"neutral": "generic_neutral_mesh", "jaw": "jawOpen", "zygomatic_major_L": "mouthSmile_L"}
    heads, regions, landmarks = {}, {}, {}
    for name, shape in shapes.items():
        lines = (shared_data / "ict-facekit" / "obj" / f"{shape}.obj").read_text().splitlines()
        (tmp_path / f"{shape}.obj").write_text("\n".join(line for line in lines if not line.startswith("mtllib")))
        heads[name] = read_scan(tmp_path / f"{shape}.obj", 10.0)  # cm
        region = 10.0 * (kit["neutral"] + (kit["deltas"][names.index(shape)] if shape in names else 0.0))
        regions[name] = Scan(region.astype(np.float64), kit["triangles"])
        landmarks[name] = landmark_set.as_dict(regions[name].points, kit["triangles"])
    assert len(heads["neutral"].points) > 2.5 * len(regions["neutral"].points)

    def build(scans):
        neutral = prepare_neutral(scans["neutral"], landmarks["neutral"], landmarks["neutral"], shape=(90, 90))
        faces = {name: prepare_expression(scans[name], landmarks[name], neutral)
                 for name in ("jaw", "zygomatic_major_L")}
        return neutral, basis_from_scans(neutral, faces)

    def errors(neutral, basis):
        """Relative RMS error of each element against ICT's own, at the true surface point of each vertex."""
        from livebridge.geometry.transforms import apply
        from livebridge.retarget.basis import relative_errors
        from livebridge.retarget.landmarks import closest_surface_points

        to_scan = np.linalg.inv(neutral.scan2face)
        triangle, bary, _ = closest_surface_points(apply(to_scan, basis.neutral), regions["neutral"].points,
                                                   kit["triangles"])
        deltas = 10.0 * kit["deltas"][[names.index(shapes[name]) for name in basis.names]] @ neutral.scan2face[:3, :3].T
        truth = np.einsum("nk,enkd->end", bary, deltas[:, kit["triangles"][triangle]])
        return relative_errors(basis.elements, truth)

    (head_neutral, head), (region_neutral, region) = build(heads), build(regions)
    assert head_neutral.grid.valid.sum() >= 0.99 * region_neutral.grid.valid.sum()
    from_head, from_region = errors(head_neutral, head), errors(region_neutral, region)
    # shape only: 0.19 / 0.53 from the head, 0.21 / 0.53 from the region (0.32 / 0.59, 0.33 / 0.59 with the
    # landmark spline alone, before scans.still_anchors); by its vertices the head gave 0.49 / 0.71
    assert (from_head < from_region + 0.02).all(), (from_head, from_region)


def test_a_mesh_expression_needs_only_the_skull_landmarks_a_point_cloud_needs(face):
    from livebridge.retarget.normalise import RIGID_LANDMARKS

    basis, landmarks = face
    neutral = _neutral(Scan(basis.neutral, basis.triangles), landmarks)
    smile = basis.neutral + basis.elements[basis.index("zygomatic_major_L")]
    skull = {name: xyz for name, xyz in load_landmark_set("builtin-22").as_dict(smile, basis.triangles).items()
             if name in RIGID_LANDMARKS}  # no chin: the face frame comes from the skull's landmarks
    expression = prepare_expression(Scan(smile, basis.triangles), skull, neutral)
    assert expression.grid.valid.sum() > 0.95 * neutral.grid.valid.sum()


def test_flying_points_are_cut_before_the_resampling(face, monkeypatch):
    """1 % of a scan's points thrown 2-20 mm off the face along the view (a depth camera's flying pixels): the
    grid is the clean scan's; without the cut, a point in front of the skin takes over its cell."""
    from livebridge.bench.scans import scan_surface
    from livebridge.retarget import face_scan

    basis, landmarks = face
    rng = np.random.default_rng(3)
    points, _, _ = scan_surface(basis.neutral, basis.triangles, 30000, 0.1, rng)
    stray = rng.random(len(points)) < 0.01
    thrown = points.copy()
    thrown[stray, 2] += rng.choice([-1.0, 1.0], stray.sum()) * rng.uniform(2.0, 20.0, stray.sum())

    def grid(cloud):
        return _neutral(Scan(cloud, np.zeros((0, 3))), landmarks).grid

    clean, cut = grid(points), grid(thrown)
    both = clean.valid & cut.valid
    assert both.sum() > 0.99 * clean.valid.sum()
    off = np.abs(cut.heights - clean.heights)[both]
    assert np.percentile(off, 99) < 0.2 and off.max() < 2.0, (np.percentile(off, 99), off.max())
    monkeypatch.setattr(face_scan, "spikes", lambda p: np.zeros(len(p), dtype=bool))
    uncut = grid(thrown)
    assert np.abs(uncut.heights - clean.heights)[both].max() > 2.0  # what the cut is for


def test_a_scan_of_a_head_turned_away_names_every_landmark_it_did_not_see(face):
    """A brow raise scanned with the head turned 60 degrees (its left side away from the scanner): the landmarks
    on skin the scanner did not see are refused all at once, named; left out of the file, the scan builds, and the
    skin the brow raise leaves still stays as still as from a frontal scan with every landmark."""
    from livebridge.bench.scans import scan_surface
    from livebridge.errors import InputError
    from livebridge.geometry.transforms import rotation_matrix
    from livebridge.retarget.scans import basis_from_scans

    basis, landmarks = face
    neutral = _neutral(Scan(basis.neutral, basis.triangles), landmarks)
    brow = basis.neutral + basis.elements[basis.index("frontalis_L")]
    truth = _truth_on_grid(basis, neutral, "frontalis_L")
    still = np.linalg.norm(truth, axis=1) < 0.01
    assert still.mean() > 0.5
    still_motion = {}
    for degrees in (0, 60):
        turn = rotation_matrix(np.array([0.0, np.radians(degrees), 0.0]))  # +x (the subject's left) away from +z
        seen, _, _ = scan_surface(brow @ turn.T, basis.triangles, 60_000, 0.0, np.random.default_rng(3))
        marks = {name: p @ turn.T for name, p in load_landmark_set("builtin-22").as_dict(brow,
                                                                                          basis.triangles).items()}
        unseen = []
        if degrees:
            with pytest.raises(InputError) as refused:
                prepare_expression(Scan(seen, np.zeros((0, 3))), marks, neutral, "brow.ply")
            unseen = [name for name in marks if name in refused.value.message or name == refused.value.field]
            assert "brow_outer_L" in unseen and all(name.endswith("_L") for name in unseen), refused.value
        expression = prepare_expression(Scan(seen, np.zeros((0, 3))), {name: p for name, p in marks.items()
                                                                        if name not in unseen}, neutral, "brow.ply")
        moved = np.linalg.norm(basis_from_scans(neutral, {"frontalis_L": expression}).elements[0], axis=1)
        still_motion[degrees] = float(np.sqrt(np.mean(moved[still] ** 2)))
    print(f"still skin moved {still_motion} mm RMS")  # 0.135 frontal, 0.077 turned
    assert still_motion[60] <= still_motion[0]


def _truth_on_grid(basis, neutral, muscle: str) -> np.ndarray:
    """``muscle``'s element of ``basis`` at the surface points closest to the grid's vertices, in the face frame
    (the neutral scanned in the basis's own frame)."""
    from livebridge.geometry.transforms import apply
    from livebridge.retarget.landmarks import closest_surface_points

    on_mesh = apply(np.linalg.inv(neutral.scan2face), neutral.mesh_vertices)
    triangle, bary, _ = closest_surface_points(on_mesh, basis.neutral, basis.triangles)
    corners = basis.elements[basis.index(muscle)][basis.triangles[triangle]]
    return np.einsum("nk,nkd->nd", bary, corners) @ neutral.scan2face[:3, :3].T


def test_the_bench_s_whole_mesh_clouds_hold_the_skin_a_frontal_scanner_does_not_see(face):
    """`livebridge bench scans`'s ``whole_mesh_clouds``: points on every triangle by its area, the back-facing
    ones too (a cloud sampled from the mesh itself); its frontal scanner's clouds have none there."""
    from livebridge.bench.scans import scan_surface
    from livebridge.face.meshio import triangle_areas, triangle_normals
    from livebridge.retarget.landmarks import closest_surface_points

    basis, _ = face
    facing_z = triangle_normals(basis.neutral, basis.triangles)[:, 2]
    areas = triangle_areas(basis.neutral, basis.triangles)
    away = facing_z < 0.0
    shares = {}
    for whole in (False, True):
        points, _, _ = scan_surface(basis.neutral, basis.triangles, 20_000, 0.0, np.random.default_rng(4), whole=whole)
        triangle, _, _ = closest_surface_points(points, basis.neutral, basis.triangles)
        shares[whole] = float(np.mean(away[triangle]))
    expected = areas[away].sum() / areas.sum()  # 0.2 on the built-in face
    assert shares[False] < 0.005
    assert abs(shares[True] - expected) < 0.03, (shares, expected)

"""Bases from scans: a neutral and 16 expression scans sampled from the ICT meshes as noisy point clouds, the
basis built from them against the ICT elements (relative RMS per element), and the time it takes.

The simulated scanner records colour: a procedural skin (:mod:`livebridge.simulators.skin`) is painted on
the NEUTRAL ICT face and carried by the mesh's own vertices into every expression, so skin that slides
along the face takes its pores, freckles and brows with it, as real skin does. Each scan sees it through
its own exposure and with colour noise."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from livebridge.bench.surface_samples import area_samples, facing_weights, triangle_samples

if TYPE_CHECKING:
    from livebridge.retarget.face_scan import FaceScan

SCAN_POINTS = 60_000
DENSE_SCAN_POINTS = 150_000
"""The bench also builds the basis from scans this dense (what a finer scanner buys)."""
SCAN_NOISE_MM = 0.2
LANDMARK_NOISE_MM = 0.5
HOLE_RADIUS_MM = 8.0
HOLE_MUSCLE = "zygomatic_major_L"
SKIN_TONE = np.array([0.93, 0.72, 0.60])
"""RGB of the skin (times the procedural albedo)."""
COLOUR_NOISE = 0.01
"""Per-point colour noise (0-1 scale)."""
EXPOSURE = 0.05
"""Each scan's brightness is off by up to this fraction."""
FLASH = (np.array([0.0, 0.0, 1.0]), 0.5)
"""The lit scans' light: a scanner's flash on its viewing axis (direction towards the light in the scanner's
frame) and the share of ambient light; the skin is Lambertian under it (see :func:`lambertian`)."""
TEXTURED_NOISE_MM = 0.1
"""Vertex noise of the simulated textured meshes (a scanner's meshing smooths its points' noise)."""
COLOUR_FOOTPRINT_MM = 1.0
"""The scanner's colour camera sees the skin through pixels this wide (the skin's finest pores blur)."""
QUICK_MUSCLES = ("frontalis_L", "zygomatic_major_L", "jaw")
"""``--quick``: these elements on a 100 x 100 grid."""
LID_MUSCLES = ("orbicularis_oculi_L", "orbicularis_oculi_R")
"""Measured again with lid landmarks added to the 22 (see ``_measure_lid_landmarks``)."""
ERROR_LIMIT = 0.10
"""The bar of issue 16: each element within 10% of its RMS displacement over the vertices it moves."""


@dataclass(frozen=True)
class SyntheticScan:
    """A simulated frontal scan of a face mesh: points and landmarks in the scanner's frame.

    Attributes
    ----------
    points : ndarray, shape (n, 3)
    landmarks : dict of str to ndarray, shape (3,)
    face2scanner : ndarray, shape (4, 4)
        Where the head was: from the mesh's frame to the scanner's.
    colours : ndarray, shape (n, 3), or None
        RGB in [0, 1] per point (None: a scanner without colour).
    triangles : ndarray of int, shape (m, 3), or None
        A textured mesh's triangles (``points`` its vertices), None for a point cloud.
    texture : Texture or None
        A textured mesh's texture (:mod:`~livebridge.retarget.texture`).
    normals : ndarray, shape (n, 3), or None
        A point cloud's unit normals, out of the surface, as its file would carry them.
    """

    points: np.ndarray
    landmarks: dict
    face2scanner: np.ndarray
    colours: np.ndarray | None = None
    triangles: np.ndarray | None = None
    texture: object = None
    normals: np.ndarray | None = None

    def as_scan(self, colour: bool = True):
        """The :class:`~livebridge.retarget.scan.Scan` a reader would give (without colour if not ``colour``)."""
        from livebridge.retarget.scan import Scan

        triangles = np.zeros((0, 3)) if self.triangles is None else self.triangles
        return Scan(self.points, triangles, self.colours if colour else None, self.texture if colour else None,
                    self.normals)


def scan_surface(vertices: np.ndarray, triangles: np.ndarray, n_points: int, noise: float,
                 rng: np.random.Generator, hole: tuple[np.ndarray, float] | None = None, skin=None,
                 exposure: float = 1.0, light: tuple[np.ndarray, float] | None = None, eyes=None,
                 whole: bool = False, normals: bool = False
                 ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Points (<= n_points, 3) a scanner looking along -z sees on a mesh, with Gaussian noise ``noise`` mm,
    and their colours (same length, 3) when ``skin`` (a :class:`~livebridge.simulators.skin.SkinTexture` of
    the mesh's vertices) is given, else None; and their unit normals (same length, 3) if ``normals``, else None:
    the mesh's vertex normals interpolated and turned by :data:`NORMAL_NOISE`, as a scanner's estimate is (the
    eyeballs' points: towards +z).

    Area-weighted random barycentric points on the triangles facing +z; hidden ones (more than 1.5 mm behind
    the front-most surface within 0.5 mm in x-y) dropped; ``hole`` = (centre (3,), radius): no points there.
    ``whole``: on every triangle, hidden or not (the lips' inner sides, the eyelids' folds, under the nose and
    chin), as a cloud sampled from the mesh itself or fused from scanners all round the head holds them.
    A point's colour is the skin at its place on the mesh (barycentric in the texels of its triangle's
    vertices) times :data:`SKIN_TONE` and ``exposure``, shaded by ``light`` (:func:`lambertian`; None: unshaded, as
    a texture a scanner has taken the lighting out of), plus :data:`COLOUR_NOISE`. ``eyes``: the head's
    :class:`~livebridge.bench.scan_eyes.Eyeballs`, seen through the eye openings (as densely, unshaded).
    """
    from scipy.ndimage import map_coordinates

    from livebridge.face.meshio import vertex_normals
    from livebridge.retarget.grid import front_surface

    points, chosen, bary = area_samples(vertices, triangles, n_points, rng, facing_only=not whole)
    keep = np.ones(len(points), dtype=bool) if whole else front_surface(points, 0.5, 1.5)
    if hole is not None:
        keep &= np.linalg.norm(points - hole[0], axis=1) > hole[1]
    points = points[keep]
    colours, point_normals, smooth = None, None, None
    if normals or (skin is not None and light is not None):  # the vertices' normals interpolated
        smooth = np.einsum("nk,nkd->nd", bary[keep], vertex_normals(vertices, triangles)[triangles[chosen[keep]]])
        smooth /= np.linalg.norm(smooth, axis=1, keepdims=True)
    if normals:
        point_normals = _noisy(smooth, rng)
    if skin is not None:
        texels = np.einsum("nk,nkd->nd", bary[keep], skin.vertex_texels[triangles[chosen[keep]]]).astype(np.float32)
        albedo = map_coordinates(skin.albedo, [texels[:, 1], texels[:, 0]], order=1, mode="nearest")
        if light is not None:  # shaded by the interpolated normals: the skin is as smooth as the mesh
            albedo = albedo * lambertian(smooth, *light)
        colours = albedo[:, None] * SKIN_TONE
    if eyes is not None:
        from livebridge.bench.scan_eyes import eye_points

        seen, eye_colours = eye_points(eyes, vertices, triangles, n_points / facing_weights(vertices, triangles).sum(),
                                       rng)
        if point_normals is not None:
            point_normals = np.vstack([point_normals, np.tile([0.0, 0.0, 1.0], (len(seen), 1))])
        points = np.vstack([points, seen])
        if skin is not None:
            colours = np.vstack([colours, eye_colours])
    points = points + rng.normal(0.0, noise, points.shape)
    if skin is not None:
        colours = np.clip(colours * exposure + rng.normal(0.0, COLOUR_NOISE, colours.shape), 0.0, 1.0)
    return points, colours, point_normals


NORMAL_NOISE = 0.05
"""Gaussian noise added to each component of a simulated scan's unit normals before they are made unit again
(about 4 degrees: a normal estimated from noisy points' neighbourhoods)."""


def _noisy(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Unit ``normals`` (n, 3) turned by :data:`NORMAL_NOISE`, unit again."""
    normals = normals + rng.normal(0.0, NORMAL_NOISE, normals.shape)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def lambertian(normals: np.ndarray, towards_light: np.ndarray, ambient: float) -> np.ndarray:
    """Lambertian shading (n,) of skin with unit ``normals`` (n, 3): ``ambient`` plus the rest times the cosine
    between the normal and ``towards_light`` (3,), unit, in the normals' frame; 0 on the far side."""
    return ambient + (1.0 - ambient) * np.clip(normals @ towards_light, 0.0, None)


def textured_mesh(vertices: np.ndarray, triangles: np.ndarray, skin, rng: np.random.Generator,
                  hole: tuple[np.ndarray, float] | None = None, exposure: float = 1.0,
                  light: tuple[np.ndarray, float] | None = None, eyes=None):
    """What a textured-mesh scanner looking along -z writes of a face mesh (``vertices`` (n, 3) in its frame):
    (vertices with :data:`TEXTURED_NOISE_MM` noise, the triangles it sees (:func:`seen_triangles`; none within
    ``hole`` = (centre, radius)), their :class:`~livebridge.retarget.texture.Texture`: ``skin`` (a
    :class:`~livebridge.simulators.skin.SkinTexture` of the mesh's vertices) times :data:`SKIN_TONE` and
    ``exposure``, shaded by ``light`` as :func:`scan_surface`'s (the vertices' shading interpolated over the
    texture), with :data:`COLOUR_NOISE` per texel). ``eyes``: (the head's
    :class:`~livebridge.bench.scan_eyes.Eyeballs`, the pose (4, 4) that put the face mesh where it is): the
    eyeball triangles seen are kept too, textured from a second image (:func:`~livebridge.bench.scan_eyes.eye_mesh`)."""
    from livebridge.retarget.texture import Texture

    noisy = vertices + rng.normal(0.0, TEXTURED_NOISE_MM, vertices.shape)
    seen = seen_triangles(noisy, triangles, rng)
    if hole is not None:
        seen &= np.linalg.norm(noisy[triangles].mean(axis=1) - hole[0], axis=1) > hole[1]
    height, width = skin.albedo.shape
    uv = np.column_stack([(skin.vertex_texels[:, 0] + 0.5) / width, 1.0 - (skin.vertex_texels[:, 1] + 0.5) / height])
    albedo = skin.albedo if light is None else skin.albedo * texel_shading(vertices, triangles, skin, *light)
    image = albedo[..., None] * SKIN_TONE * exposure + rng.normal(0.0, COLOUR_NOISE, (height, width, 3))
    kept = triangles[seen]
    texture = Texture(uv[kept], np.zeros(len(kept), np.int64), (np.clip(image, 0, 1).astype(np.float32),),
                      ("skin.png",))
    if eyes is None:
        return noisy, kept, texture
    from livebridge.bench.scan_eyes import eye_mesh

    eye_vertices, eye_triangles, eye_uv, eye_image = eye_mesh(*eyes, vertices, triangles, rng, exposure)
    eye_image = np.clip(eye_image + rng.normal(0.0, COLOUR_NOISE, eye_image.shape), 0, 1).astype(np.float32)
    texture = Texture(np.concatenate([texture.uv, eye_uv]),
                      np.concatenate([texture.image_index, np.ones(len(eye_triangles), np.int64)]),
                      texture.images + (eye_image,), texture.names + ("eyes.png",))
    noisy = np.vstack([noisy, eye_vertices + rng.normal(0.0, TEXTURED_NOISE_MM, eye_vertices.shape)])
    return noisy, np.vstack([kept, eye_triangles + len(vertices)]), texture


def texel_shading(vertices: np.ndarray, triangles: np.ndarray, skin, towards_light: np.ndarray,
                  ambient: float) -> np.ndarray:
    """:func:`lambertian` shading of a mesh's vertices (``vertices`` (n, 3), in the light's frame) spread over
    its texture ``skin``'s texels (rows, columns) by linear interpolation between the vertices' texels; 1 on
    texels no vertex reaches."""
    from scipy.interpolate import LinearNDInterpolator

    from livebridge.face.meshio import vertex_normals

    on_vertex = lambertian(vertex_normals(vertices, triangles), towards_light, ambient)
    rows, columns = np.mgrid[0:skin.albedo.shape[0], 0:skin.albedo.shape[1]]
    shade = LinearNDInterpolator(skin.vertex_texels, on_vertex, fill_value=1.0)(columns, rows)
    return shade.astype(np.float32)


def seen_triangles(vertices: np.ndarray, triangles: np.ndarray, rng: np.random.Generator,
                   samples: int = 16) -> np.ndarray:
    """Mask (m,) of the triangles a scanner looking along -z sees (what its mesh keeps): facing +z, and at
    least half of ``samples`` random points on each on the front surface (as :func:`scan_surface` keeps
    points)."""
    from livebridge.retarget.grid import front_surface

    facing = np.flatnonzero(facing_weights(vertices, triangles) > 0)
    points = triangle_samples(vertices, triangles[facing], samples, rng)
    seen = front_surface(points.reshape(-1, 3), 0.5, 1.5).reshape(len(facing), samples).mean(axis=1) >= 0.5
    mask = np.zeros(len(triangles), bool)
    mask[facing[seen]] = True
    return mask


def random_pose(rng: np.random.Generator, degrees: float = 10.0, shift_mm: float = 30.0) -> np.ndarray:
    """A random rigid motion (4, 4): rotation up to ``degrees`` about a random axis, shift up to ``shift_mm``."""
    from livebridge.geometry.transforms import rotation_matrix

    axis = rng.normal(size=3)
    pose = np.eye(4)
    pose[:3, :3] = rotation_matrix(axis / np.linalg.norm(axis) * np.radians(degrees) * rng.random())
    pose[:3, 3] = rng.uniform(-shift_mm, shift_mm, 3)
    return pose


def synthetic_scans(basis, landmarks, rng: np.random.Generator, n_points: int = SCAN_POINTS,
                    noise: float = SCAN_NOISE_MM, landmark_noise: float = LANDMARK_NOISE_MM,
                    hole_muscle: str | None = HOLE_MUSCLE, colour: bool = True,
                    muscles=None, textured: bool = False, lit: bool = False, eyes=None, whole: bool = False,
                    normals: bool = False) -> tuple[SyntheticScan, dict[str, SyntheticScan]]:
    """(neutral, {muscle: expression}) scans of ``basis`` (each element fully contracted), each with its own
    random head pose, sampling, noise and exposure; landmarks from ``landmarks`` (a LandmarkSet on the basis)
    plus Gaussian noise. The ``hole_muscle`` scan has a hole of :data:`HOLE_RADIUS_MM` on that side's cheek.
    ``colour``: the scans carry the skin painted on the neutral face; ``muscles``: only these (default all).
    ``textured``: each scan is instead the mesh a scanner would write (:func:`textured_mesh`: the triangles it
    sees, vertices with :data:`TEXTURED_NOISE_MM` noise, the skin as its texture; ``n_points`` unused).
    ``lit``: the colours (or the texture) shaded by the scanner's :data:`FLASH`, fixed in the scanner's frame,
    so the shading changes with each scan's head pose and with the expression's shape. ``eyes``: the head's
    :class:`~livebridge.bench.scan_eyes.Eyeballs` (fixed in the skull), which the scans also see through the eye
    openings (unlit). ``whole``: each point cloud sampled over the whole mesh, the skin the front hides too
    (:func:`scan_surface`); ``normals``: each point cloud with its points' normals."""
    from livebridge.geometry.transforms import apply
    from livebridge.simulators.skin import make_skin

    skin = None
    if colour or textured:
        skin = make_skin(basis.neutral, int(rng.integers(1 << 30)), landmarks.as_dict(basis.neutral, basis.triangles))
        skin = skin.level(COLOUR_FOOTPRINT_MM)

    def one(shape, hole=None):
        pose = random_pose(rng)
        exposure = 1.0 + rng.uniform(-EXPOSURE, EXPOSURE)
        if textured:
            seen_hole = None if hole is None else (apply(pose, hole[0][None])[0], hole[1])
            mesh = textured_mesh(apply(pose, shape), basis.triangles, skin, rng, seen_hole, exposure,
                                 FLASH if lit else None, None if eyes is None else (eyes, pose))
        else:
            light = (pose[:3, :3].T @ FLASH[0], FLASH[1]) if lit else None  # the flash in the mesh's frame
            points, colours, point_normals = scan_surface(shape, basis.triangles, n_points, noise, rng, hole, skin,
                                                          exposure, light, eyes, whole, normals)
        marks = landmarks.as_dict(shape, basis.triangles)
        marks = {name: apply(pose, p[None])[0] + rng.normal(0.0, landmark_noise, 3) for name, p in marks.items()}
        if textured:
            return SyntheticScan(mesh[0], marks, pose, None, mesh[1], mesh[2])
        turned = None if point_normals is None else point_normals @ pose[:3, :3].T
        return SyntheticScan(apply(pose, points), marks, pose, colours, normals=turned)

    neutral = one(basis.neutral)
    expressions = {}
    for muscle, element in zip(basis.muscles, basis.elements):
        if muscles is not None and muscle.name not in muscles:
            continue
        hole = None
        if muscle.name == hole_muscle:
            at = landmarks.as_dict(basis.neutral + element, basis.triangles)
            side = muscle.side or "L"
            hole = (0.5 * (at[f"mouth_corner_{side}"] + at[f"eye_outer_{side}"]), HOLE_RADIUS_MM)
        expressions[muscle.name] = one(basis.neutral + element, hole)
    return neutral, expressions


def truth_on_grid(basis, neutral_scan: SyntheticScan, face, names) -> np.ndarray:
    """The basis's elements at the points of its neutral surface closest to the built neutral mesh's vertices
    (:attr:`~livebridge.retarget.face_scan.FaceScan.mesh_vertices`), in the face frame.

    ``face`` is the prepared neutral (:class:`~livebridge.retarget.face_scan.FaceScan`); returns (k, n_vertices, 3).
    """
    from livebridge.geometry.transforms import apply
    from livebridge.retarget.landmarks import closest_surface_points

    mesh2face = face.scan2face @ neutral_scan.face2scanner
    on_mesh = apply(np.linalg.inv(mesh2face), face.mesh_vertices)
    triangle, bary, _ = closest_surface_points(on_mesh, basis.neutral, basis.triangles)
    index = [basis.index(name) for name in names]
    corners = basis.elements[index][:, basis.triangles[triangle]]  # (k, n, 3 corners, 3)
    return np.einsum("nk,enkd->end", bary, corners) @ mesh2face[:3, :3].T


def surface_errors(built: np.ndarray, vertices: np.ndarray, basis, neutral_scan: SyntheticScan, face,
                   names, truth: np.ndarray) -> np.ndarray:
    """Per element, how far the expression the built basis gives (``vertices + built``) is from the true
    expressive surface: the RMS distance to the ICT expression mesh (in the face frame) over the vertices the
    element moves, over the element's RMS displacement there (as in ``relative_errors``); shape (k,).

    ``built``, ``truth``: (k, n_vertices, 3); ``face``: the prepared neutral.
    """
    from livebridge.geometry.transforms import apply
    from livebridge.retarget.basis import MOVED_FRACTION
    from livebridge.retarget.landmarks import surface_values

    mesh2face = face.scan2face @ neutral_scan.face2scanner
    out = np.full(len(names), np.nan)
    for k, name in enumerate(names):
        expressive = apply(mesh2face, basis.neutral + basis.elements[basis.index(name)])
        points = vertices + built[k]
        distance = np.linalg.norm(points - surface_values(points, expressive, basis.triangles, expressive), axis=1)
        size = np.linalg.norm(truth[k], axis=1)
        moved = size > MOVED_FRACTION * size.max()
        out[k] = np.sqrt(np.mean(distance[moved] ** 2) / np.mean(size[moved] ** 2))
    return out


@dataclass(frozen=True)
class ScanFigures:
    """What :func:`build_and_measure` measured; error arrays have one value per element (``names``)."""

    names: tuple
    n_vertices: int
    truth: np.ndarray
    with_colour: np.ndarray
    without_colour: np.ndarray
    errors: np.ndarray
    errors_without_colour: np.ndarray
    surface: np.ndarray
    surface_without_colour: np.ndarray
    build_s: float
    build_without_colour_s: float
    gaps: np.ndarray
    """Per element, its scan's distance from the neutral's surface over the limit of
    :func:`~livebridge.retarget.same_face.another_face` (over 1: told as another face)."""
    neutral: FaceScan | None = None
    """The prepared neutral the basis was built on."""


def build_and_measure(basis, landmarks, rng: np.random.Generator, grid: tuple[int, int] | None = None,
                      remove_shading: bool | None = None, leave_out_eyeballs: bool = True,
                      **scan_options) -> ScanFigures:
    """Coloured scans of ``basis`` (unless ``colour=False`` among ``scan_options``; ``landmarks`` the 22 or a
    68-point set); the basis built from them with skin tracking and from shape alone (the same prepared scans,
    colour ignored); each against the ICT elements and the true expressive surfaces. ``remove_shading``,
    ``leave_out_eyeballs``: as :func:`~livebridge.retarget.face_scan.prepare_neutral`'s."""
    from livebridge.retarget.basis import relative_errors
    from livebridge.retarget.face_scan import prepare_expression, prepare_neutral
    from livebridge.retarget.grid import GRID_SHAPE
    from livebridge.retarget.landmarks import thesis_points_from_68
    from livebridge.retarget.same_face import gap_limit
    from livebridge.retarget.scans import basis_from_scans

    neutral_scan, expression_scans = synthetic_scans(basis, landmarks, rng, **scan_options)
    # a 68-point set's own face as the reference too, named as the thesis's 22 (as the scans' landmarks are)
    reference = thesis_points_from_68(landmarks.as_dict(basis.neutral, basis.triangles), basis.neutral)
    start = time.perf_counter()
    neutral = prepare_neutral(neutral_scan.as_scan(), neutral_scan.landmarks, reference, shape=grid or GRID_SHAPE,
                              remove_shading=remove_shading, leave_out_eyeballs=leave_out_eyeballs)
    faces = {name: prepare_expression(s.as_scan(), s.landmarks, neutral, name) for name, s in expression_scans.items()}
    prepared = time.perf_counter() - start
    start = time.perf_counter()
    coloured = basis_from_scans(neutral, faces)
    colour_s = time.perf_counter() - start
    start = time.perf_counter()
    shape_only = basis_from_scans(neutral, faces, colour=False)
    shape_s = time.perf_counter() - start
    names = coloured.names
    truth = truth_on_grid(basis, neutral_scan, neutral, names)

    def surface(built):
        return surface_errors(built.elements, built.neutral, basis, neutral_scan, neutral, names, truth)

    gaps = np.array([faces[name].gap_mm / gap_limit(faces[name].noise_mm) for name in names])
    return ScanFigures(names, coloured.n_vertices, truth, coloured.elements, shape_only.elements,
                       relative_errors(coloured.elements, truth), relative_errors(shape_only.elements, truth),
                       surface(coloured), surface(shape_only), prepared + colour_s, prepared + shape_s, gaps, neutral)


def run(quick: bool, log) -> dict:
    from livebridge.bench.data import ict_basis, ict_eyeballs

    basis = ict_basis()
    if basis is None:
        log("scans: the ICT reference data (../shared/data) is not here; nothing to measure")
        return {"skipped": "no ICT reference data"}
    options = {"grid": (100, 100), "muscles": QUICK_MUSCLES} if quick else {}
    result = _measure_density(basis, SCAN_POINTS, options, log)
    if not quick:
        result[f"at_{DENSE_SCAN_POINTS}_points"] = _measure_density(basis, DENSE_SCAN_POINTS, options, log)
        result["eyelids_with_lid_landmarks"] = _measure_lid_landmarks(basis, log)
        result["textured_meshes"] = _measure(basis, "textured meshes (the triangles a scanner sees, 0.1 mm vertex "
                                             "noise, the skin as their texture)", {"textured": True}, log)
        result["lit_scans"] = _measure_lit(basis, f"lit by the scanner's flash, {SCAN_POINTS} points a scan",
                                           {"n_points": SCAN_POINTS}, log)
        result["lit_textured_meshes"] = _measure_lit(basis, "textured meshes lit by the scanner's flash",
                                                     {"textured": True}, log)
        result["other_proportions"] = _measure_other_face(basis, log)
        result["whole_mesh_clouds"] = _measure_density(basis, SCAN_POINTS, {"whole": True}, log,
                                                       "clouds sampled over the whole mesh, the skin the front hides "
                                                       "too")
        result["whole_mesh_clouds_with_normals"] = _measure_density(
            basis, SCAN_POINTS, {"whole": True, "normals": True}, log,
            "clouds sampled over the whole mesh with their normals (those facing away from the front left out)")
        eyes = ict_eyeballs()
        if eyes is not None:
            result["scanned_eyes"] = _measure_scanned_eyes(basis, eyes, log)
    return result


def _measure_scanned_eyes(basis, eyes, log) -> dict:
    """The figures for scans that also see the head's ``eyes`` (:class:`~livebridge.bench.scan_eyes.Eyeballs`)
    through the eye openings, as a real scanner does (the eyeballs left out by their colour:
    :mod:`~livebridge.retarget.eyeballs`), and the errors with the eyeballs kept in the scans."""
    return _measure_against(basis, f"the eyes seen between the lids, {SCAN_POINTS} points a scan",
                            {"n_points": SCAN_POINTS, "eyes": eyes}, log, {"leave_out_eyeballs": False},
                            "with the eyeballs kept", "eyeballs_kept")


def _measure_other_face(basis, log) -> dict:
    """The same figures for another person's face: the ICT face and its elements under the retarget bench's
    known warp (:func:`~livebridge.bench.retarget.known_warp`: narrower, taller and flatter, a wider mouth, a
    longer nose), scanned as the ICT face is; of the scan pipeline's settings only the outline's reach
    (:data:`~livebridge.retarget.skin_flow.OUTLINE_MM`) and the way a closing eye's hole is filled for the flow
    (:func:`~livebridge.retarget.skin_flow.closing_holes`) were chosen with this face among the draws measured."""
    from livebridge.bench.retarget import warped_basis
    from livebridge.retarget.landmarks import load_landmark_set

    other = warped_basis(basis, load_landmark_set("ict-22").as_dict(basis.neutral, basis.triangles))
    return _measure_density(other, SCAN_POINTS, {}, log, "another face (the ICT face under the known warp)")


def _measure_lit(basis, what: str, options: dict, log) -> dict:
    """The figures for scans (made with ``options``; ``what`` they are, for the log) whose colours hold the
    scanner's :data:`FLASH` (the shading divided out as ``retarget scans --lighting auto`` decides), and the
    errors with the shading left in the colours."""
    return _measure_against(basis, what, options | {"lit": True}, log, {"remove_shading": False},
                            "with their shading left in the colours", "shading_kept")


def _measure_against(basis, what: str, options: dict, log, without: dict, said: str, suffix: str) -> dict:
    """The figures for scans made with ``options`` (``what`` they are, for the log), and the errors of the same
    scans built with ``without`` (:func:`build_and_measure`'s keywords: a step of the pipeline left out; logged
    as built ``said``), as ``max_relative_error_<suffix>`` and ``relative_errors_<suffix>``."""
    from livebridge.retarget.landmarks import load_landmark_set

    result = _measure(basis, what, options, log)
    other = build_and_measure(basis, load_landmark_set("ict-22"), np.random.default_rng(7), **without, **options)
    log(f"  the same scans {said}:")
    for name, error in zip(other.names, other.errors):
        log(f"  {name:24s} error {error:.3f}")
    return result | {f"max_relative_error_{suffix}": float(np.nanmax(other.errors)),
                     f"relative_errors_{suffix}": dict(zip(other.names, (round(float(v), 4) for v in other.errors)))}


def _measure_lid_landmarks(basis, log) -> dict:
    """The eyelid elements again with the 22 landmarks plus the 8 lid points of the 68-point layout (what a
    landmark detector run on each scan's texture gives; the 22-landmark figures above are the thesis's)."""
    from livebridge.retarget.eyelids import LID_LANDMARK_NAMES
    from livebridge.retarget.landmarks import load_landmark_set

    lids = list(LID_LANDMARK_NAMES)
    landmarks = with_landmarks(load_landmark_set("ict-22"), load_landmark_set("ict-68"), lids)
    figures = build_and_measure(basis, landmarks, np.random.default_rng(7), muscles=LID_MUSCLES)
    log(f"scans, eyelids with the 22 landmarks plus the lid landmarks {', '.join(lids)} ({SCAN_POINTS} points):")
    for name, error in zip(figures.names, figures.errors):
        log(f"  {name:24s} error {error:.3f}")
    return {"landmarks": ["22 thesis"] + lids, "scan_points": SCAN_POINTS,
            "relative_errors": dict(zip(figures.names, (round(float(v), 4) for v in figures.errors)))}


def with_landmarks(landmarks, more, names):
    """``landmarks`` (a LandmarkSet) plus the landmarks ``names`` of ``more`` (on the same mesh)."""
    from livebridge.retarget.landmarks import LandmarkSet

    index = more.index_of(names)
    return LandmarkSet(landmarks.names + tuple(names), np.concatenate([landmarks.triangles, more.triangles[index]]),
                       np.concatenate([landmarks.barycentric, more.barycentric[index]]),
                       landmarks.regions + tuple(more.regions[i] for i in index),
                       landmarks.roles + tuple(more.roles[i] for i in index), landmarks.mesh_triangles)


def _measure_density(basis, n_points: int, options: dict, log, face: str = "") -> dict:
    """The figures of one bench run with scans of ``n_points`` points each (of ``face``, for the log), as the
    JSON result."""
    what = f"{face}, {n_points} points a scan" if face else f"{n_points} points a scan"
    return {"scan_points": n_points} | _measure(basis, what, options | {"n_points": n_points}, log)


def _measure(basis, what: str, options: dict, log) -> dict:
    """The figures of one bench run with scans made with ``options`` (of :func:`synthetic_scans`; ``what`` they
    are, for the log), as the JSON result."""
    from livebridge.retarget.landmarks import load_landmark_set
    from livebridge.retarget.shading import lighting_said

    figures = build_and_measure(basis, load_landmark_set("ict-22"), np.random.default_rng(7), **options)
    log(f"scans: {what}, {figures.n_vertices} grid vertices, {len(figures.names)} elements; "
        f"built in {figures.build_s:.1f} s with skin tracking, {figures.build_without_colour_s:.1f} s from shape "
        "alone")
    if figures.neutral.shading is not None:
        log(f"  {lighting_said(figures.neutral.shading, figures.neutral.shading_removed)}")
    if figures.neutral.eyeball_points:
        log(f"  {figures.neutral.eyeball_points} points of the neutral were eyeballs, left out")
    log(f"  {'element':24s} {'RMS mm':>7s} {'error':>7s} {'no colour':>9s} {'surface':>8s} {'no colour':>9s}")
    for k, name in enumerate(figures.names):
        size = np.linalg.norm(figures.truth[k], axis=1)
        rms = float(np.sqrt(np.mean(size[size > 0.01 * size.max()] ** 2)))
        flag = "" if figures.errors[k] <= ERROR_LIMIT else f"  > {ERROR_LIMIT}"
        log(f"  {name:24s} {rms:7.2f} {figures.errors[k]:7.3f} {figures.errors_without_colour[k]:9.3f} "
            f"{figures.surface[k]:8.3f} {figures.surface_without_colour[k]:9.3f}{flag}")

    def per_element(values):
        return dict(zip(figures.names, (round(float(v), 4) for v in values)))

    shading = figures.neutral.shading

    return {"n_vertices": figures.n_vertices, "limit": ERROR_LIMIT,
            "build_s": figures.build_s, "build_without_colour_s": figures.build_without_colour_s,
            "max_relative_error": float(np.nanmax(figures.errors)),
            "max_relative_error_without_colour": float(np.nanmax(figures.errors_without_colour)),
            "max_surface_error": float(np.nanmax(figures.surface)),
            "max_surface_error_without_colour": float(np.nanmax(figures.surface_without_colour)),
            "relative_errors": per_element(figures.errors),
            "relative_errors_without_colour": per_element(figures.errors_without_colour),
            "surface_errors": per_element(figures.surface),
            "surface_errors_without_colour": per_element(figures.surface_without_colour),
            "gaps_over_limit": per_element(figures.gaps),
            "shading_removed": figures.neutral.shading_removed,
            "shading_explained": None if shading is None else round(shading.explained, 3),
            "eyeball_points_left_out": figures.neutral.eyeball_points,
            "told_another_face": [name for name, gap in zip(figures.names, figures.gaps) if gap > 1]}

"""Normalisation of a face image: head pose from the LED head rig, warp to the canonical pose, lighting.

Head pose
    The four LEDs of the head rig (on an empty glasses frame) are the brightest blobs of the image
    (:func:`livebridge.reconstruct.detect.detect_blobs`, as for markers). They are matched to the rig's LEDs
    by their projection at the previous pose (Hungarian assignment), or, with no previous pose, by trying
    every assignment and keeping the one that reprojects best with the face towards the camera; the pose
    is ``cv2.solvePnP`` on the rig geometry (refined from the previous pose; IPPE or SQPnP without one).
Warp
    Each pixel of the canonical image shows a point of the head frame (:func:`canonical_surface`): on the
    face mesh when the model was trained with one (the basis's neutral face, in the rig's frame), else on a
    plane through the rig facing the camera (then the warp is that plane's homography). Per frame every
    canonical pixel samples the camera image where its point projects at the current pose.
Lighting
    The Laplacian of the (slightly blurred) logarithm of the image: the log turns the illumination factor
    into an additive term, which is smooth over skin and removed by the Laplacian, so neither exposure
    nor a drifting light direction reaches the signatures (the paper filters the image itself; ``log=False``
    does that).
``head_rig = "none"`` (head-mounted camera, chin rest): the canonical image is a fixed crop.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from livebridge.errors import InputError

N_LEDS = 4
LOG_OFFSET = 16.0  # grey levels


@dataclass(frozen=True, eq=False)
class HeadRig:
    """The LED head rig.

    Attributes
    ----------
    leds : ndarray, shape (4, 3)
        LED positions in the head frame, mm.
    face_point : ndarray, shape (3,)
        A point of the plane that stands for the face in the warp (head frame, mm).
    face_normal : ndarray, shape (3,)
        Its unit normal, pointing out of the face (towards the camera at the canonical pose).
    """

    leds: np.ndarray
    face_point: np.ndarray
    face_normal: np.ndarray

    @classmethod
    def from_leds(cls, leds: np.ndarray, face_normal=(0.0, 0.0, 1.0), face_offset_mm: float = 0.0) -> HeadRig:
        """A rig whose face plane passes ``face_offset_mm`` behind the LEDs' centroid, normal ``face_normal``."""
        leds = np.asarray(leds, dtype=np.float64)
        if leds.shape != (N_LEDS, 3) or not np.isfinite(leds).all():
            raise ValueError(f"leds must be a finite (4, 3) array, got shape {leds.shape}")
        normal = np.asarray(face_normal, dtype=np.float64)
        normal = normal / np.linalg.norm(normal)
        return cls(leds, leds.mean(axis=0) - face_offset_mm * normal, normal)


def load_head_rig(path: str | Path) -> HeadRig:
    """Read a head-rig TOML: a ``[leds]`` table of four named LED positions ``name = [x, y, z]`` (mm, head
    frame: the face model's, +z out of the face); optional top-level ``face_normal`` (3 numbers, default
    ``[0, 0, 1]``) and ``face_offset_mm`` (default 0) place the face plane the warp falls back to."""
    from livebridge.tomlio import load_toml, require

    table = load_toml(path)
    leds_table = require(table, "leds", dict, path)
    if len(leds_table) != N_LEDS:
        raise InputError(f"a head rig has exactly {N_LEDS} LEDs, got {len(leds_table)}", path, "leds")
    leds = np.array([_numbers(value, (3,), path, f"leds.{name}") for name, value in leds_table.items()])
    normal = _numbers(table.get("face_normal", [0.0, 0.0, 1.0]), (3,), path, "face_normal")
    if np.linalg.norm(normal) == 0:
        raise InputError("must not be zero", path, "face_normal")
    offset = table.get("face_offset_mm", 0.0)
    if isinstance(offset, bool) or not isinstance(offset, (int, float)) or not np.isfinite(offset):
        raise InputError(f"expected a number, got {offset!r}", path, "face_offset_mm")
    if np.linalg.svd(leds - leds.mean(axis=0), compute_uv=False)[1] < 1.0:
        raise InputError("the four LEDs lie on one line: a pose needs them spread over a plane", path, "leds")
    return HeadRig.from_leds(leds, normal, float(offset))


def _numbers(value, shape: tuple[int, ...], path, name: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"expected numbers of shape {shape}, got {value!r}", path, name) from None
    if array.shape != shape or not np.isfinite(array).all():
        raise InputError(f"expected finite numbers of shape {shape}, got {value!r}", path, name)
    return array


@dataclass(frozen=True, eq=False)
class Normalisation:
    """How a camera image becomes a canonical face image (stored in the model).

    Attributes
    ----------
    input_size : tuple of int
        Camera image ``(width, height)``.
    head_rig : HeadRig or None
        None: no head rig; the canonical image is ``crop``.
    camera_matrix : ndarray, shape (3, 3)
    distortions : ndarray, shape (5,)
    canonical_head2cam : ndarray, shape (4, 4) or None
        The head pose the canonical image shows (set by training).
    crop : tuple of int
        ``(x, y, width, height)`` of the canonical image in the camera image (whole image by default);
        with a head rig, applied after the warp.
    surface : ndarray, shape (H, W, 3), float32, or None
        Per pixel of the (uncropped) canonical image, the head-frame point it shows: the face mesh where one
        was given at training, the face plane elsewhere (set with the canonical pose).
    pose_warp : bool
        False (ablation): the pose is measured but the image is not warped.
    laplacian : bool
        False (ablation): no lighting normalisation.
    log : bool
        Laplacian of the log image (see the module docstring).
    blur_sigma : float
        Gaussian blur before the Laplacian, pixels.
    clip : float or None
        The filtered image is clipped to ``[-clip, clip]`` (set by training from the neutral face: a few robust
        deviations), so the rig's dark frame edges and bright LEDs, and specular highlights, cannot outweigh
        the skin's texture in a region's signature.
    """

    input_size: tuple[int, int]
    head_rig: HeadRig | None = None
    camera_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    distortions: np.ndarray = field(default_factory=lambda: np.zeros(5))
    canonical_head2cam: np.ndarray | None = None
    crop: tuple[int, int, int, int] | None = None
    surface: np.ndarray | None = None
    pose_warp: bool = True
    laplacian: bool = True
    log: bool = True
    blur_sigma: float = 1.0
    clip: float | None = None

    def __post_init__(self):
        width, height = (int(v) for v in self.input_size)
        object.__setattr__(self, "input_size", (width, height))
        object.__setattr__(self, "camera_matrix", np.asarray(self.camera_matrix, dtype=np.float64))
        object.__setattr__(self, "distortions", np.asarray(self.distortions, dtype=np.float64).ravel())
        crop = (0, 0, width, height) if self.crop is None else tuple(int(v) for v in self.crop)
        x, y, w, h = crop
        if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > width or y + h > height:
            raise ValueError(f"crop {crop} does not fit in a {width}x{height} image")
        object.__setattr__(self, "crop", crop)

    @property
    def image_size(self) -> tuple[int, int]:
        """Canonical image ``(width, height)``."""
        return self.crop[2], self.crop[3]

    def with_canonical(self, head2cam: np.ndarray, vertices: np.ndarray | None = None,
                       triangles: np.ndarray | None = None) -> Normalisation:
        """This normalisation with its canonical pose ``head2cam (4, 4)`` and the surface the warp follows:
        the face mesh (``vertices (n, 3)`` mm in the head frame, ``triangles (m, 3)``) where given, else the
        face plane of the rig."""
        head2cam = np.asarray(head2cam, dtype=np.float64)
        norm = replace(self, canonical_head2cam=head2cam)
        return replace(norm, surface=canonical_surface(norm, head2cam, vertices, triangles))


def default_camera_matrix(size: tuple[int, int]) -> np.ndarray:
    """A pinhole guess for an uncalibrated webcam: focal length the image width, centre the image centre."""
    width, height = size
    return np.array([[width, 0.0, (width - 1) / 2], [0.0, width, (height - 1) / 2], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class PoseState:
    """Between frames: the last head pose found (``head2cam (4, 4)``) or None."""

    head2cam: np.ndarray | None = None


def _gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image


def detect_leds(image: np.ndarray) -> np.ndarray:
    """Bright blob centroids (LED candidates), shape (n, 2) pixels, brightest first."""
    from livebridge.reconstruct.detect import DetectConfig, detect_blobs

    gray = _gray(image)
    points = detect_blobs(gray, DetectConfig(contrast=0.9, min_area=2, max_area=400))
    if len(points) > 1:
        x = np.clip(np.rint(points).astype(int), 0, [gray.shape[1] - 1, gray.shape[0] - 1])
        points = points[np.argsort(-gray[x[:, 1], x[:, 0]].astype(np.float64), kind="stable")]
    return points


def _pnp(leds: np.ndarray, points: np.ndarray, norm: Normalisation,
         guess: np.ndarray | None = None) -> tuple[np.ndarray | None, float]:
    """(head2cam, RMS reprojection error in px) of one LED assignment, or (None, inf).

    Four LEDs on a glasses frame are (nearly) coplanar, where a pose and its mirror about the line of sight
    fit almost equally well: with a previous pose (``guess``) the pose is refined from it (continuity);
    without, every solution is tried and the one facing the camera most squarely wins.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    if guess is not None:
        ok, rvec, tvec = cv2.solvePnP(leds, points, norm.camera_matrix, norm.distortions,
                                      cv2.Rodrigues(guess[:3, :3])[0], guess[:3, 3].copy(),
                                      useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        candidates = [(rvec, tvec)] if ok else []
    else:
        flags = cv2.SOLVEPNP_IPPE if _coplanar(leds) else cv2.SOLVEPNP_SQPNP
        count, rvecs, tvecs, _ = cv2.solvePnPGeneric(leds, points, norm.camera_matrix, norm.distortions,
                                                     flags=flags)
        candidates = list(zip(rvecs, tvecs))[:count]
    best, best_key = None, (np.inf, np.inf)
    for rvec, tvec in candidates:
        head2cam = np.eye(4)
        head2cam[:3, :3] = cv2.Rodrigues(rvec)[0]
        head2cam[:3, 3] = np.ravel(tvec)
        facing = (head2cam[:3, :3] @ norm.head_rig.face_normal)[2]  # < 0: the face looks at the camera
        if head2cam[2, 3] <= 0 or facing >= 0:
            continue
        projected = cv2.projectPoints(leds, rvec, tvec, norm.camera_matrix, norm.distortions)[0].reshape(-1, 2)
        error = float(np.sqrt(np.mean(np.sum((projected - points) ** 2, axis=1))))
        key = (0.0 if error <= 1.0 else error, facing)
        if key < best_key:
            best, best_key = (head2cam, error), key
    return best if best is not None else (None, np.inf)


def _coplanar(points: np.ndarray) -> bool:
    centred = points - points.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    return bool(singular[-1] < 1e-3 * singular[0])


def estimate_head_pose(image: np.ndarray, norm: Normalisation, state: PoseState = PoseState(),
                       max_error_px: float = 2.0, candidates: np.ndarray | None = None
                       ) -> tuple[PoseState, np.ndarray | None]:
    """The head pose of one image from its LEDs.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
    norm : Normalisation
        With a head rig.
    state : PoseState
        The previous pose (for the LED assignment).
    max_error_px : float
        A pose whose LEDs reproject worse than this (RMS) is refused.
    candidates : ndarray, shape (n, 2), optional
        The image's LED candidates already found (:func:`detect_leds`, e.g. on the camera's reader thread);
        None: found here.

    Returns
    -------
    (PoseState, head2cam (4, 4) or None)
        None when fewer than four LEDs are seen or no assignment fits: the LEDs are lost.
    """
    leds = norm.head_rig.leds
    points = detect_leds(image) if candidates is None else candidates
    if len(points) < N_LEDS:
        return PoseState(None), None
    previous = state.head2cam if state.head2cam is not None else norm.canonical_head2cam
    if previous is not None:
        predicted = cv2.projectPoints(leds, cv2.Rodrigues(previous[:3, :3])[0], previous[:3, 3],
                                      norm.camera_matrix, norm.distortions)[0].reshape(-1, 2)
        cost = np.linalg.norm(predicted[:, None] - points[None], axis=2)
        rows, cols = linear_sum_assignment(cost)
        head2cam, error = _pnp(leds, points[cols[np.argsort(rows)]], norm, previous)
        if error <= max_error_px:
            return PoseState(head2cam), head2cam
    head2cam, error = _best_assignment(leds, points[:8], norm)
    if error > max_error_px:
        return PoseState(None), None
    return PoseState(head2cam), head2cam


def _best_assignment(leds: np.ndarray, points: np.ndarray, norm: Normalisation) -> tuple[np.ndarray | None, float]:
    best, best_error = None, np.inf
    for chosen in itertools.permutations(range(len(points)), N_LEDS):
        head2cam, error = _pnp(leds, points[list(chosen)], norm)
        if error < best_error:
            best, best_error = head2cam, error
    return best, best_error


def canonical_surface(norm: Normalisation, head2cam: np.ndarray, vertices: np.ndarray | None = None,
                      triangles: np.ndarray | None = None) -> np.ndarray:
    """The head-frame point each canonical pixel shows, shape (H, W, 3) float32.

    Rays through the pixels (at the canonical pose ``head2cam``) meet the rig's face plane; where a face mesh
    is given, its front-facing vertices projected to the image and interpolated (linear, over their
    Delaunay triangulation) give the point instead, so the warp follows the face's relief (nose, eye
    sockets) rather than a plane when the head turns.
    """
    width, height = norm.input_size
    rotation, translation = head2cam[:3, :3], head2cam[:3, 3]
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(norm.camera_matrix).T
    normal = rotation @ norm.head_rig.face_normal
    point = rotation @ norm.head_rig.face_point + translation
    cam = rays * ((normal @ point) / (rays @ normal))[..., None]
    surface = (cam - translation) @ rotation  # camera -> head: R^T (x - t)
    if vertices is not None and triangles is not None:
        from scipy.interpolate import griddata

        from livebridge.face.meshio import vertex_normals

        vertices = np.asarray(vertices, dtype=np.float64)
        cam_vertices = vertices @ rotation.T + translation
        facing = np.einsum("ij,ij->i", vertex_normals(vertices, triangles) @ rotation.T, cam_vertices) < 0
        facing &= cam_vertices[:, 2] > 0
        pixels = cam_vertices[facing] @ norm.camera_matrix.T
        pixels = pixels[:, :2] / pixels[:, 2:]
        on_mesh = griddata(pixels, vertices[facing], (u, v), method="linear")
        covered = np.isfinite(on_mesh).all(axis=-1)
        surface[covered] = on_mesh[covered]
    return surface.astype(np.float32)


def warp_to_canonical(image: np.ndarray, norm: Normalisation, head2cam: np.ndarray) -> np.ndarray:
    """The image as seen at the canonical pose, same size as ``image``: each canonical pixel samples the
    image where its surface point (``norm.surface``) projects at the pose ``head2cam``."""
    projection = (norm.camera_matrix @ head2cam[:3]).astype(np.float32)  # (3, 4)
    surface = norm.surface
    pixels = surface @ projection[:, :3].T + projection[:, 3]
    depth = pixels[..., 2]
    map_x = pixels[..., 0] / depth
    map_y = pixels[..., 1] / depth
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def lighting_normalise(image: np.ndarray, blur_sigma: float = 1.0, log: bool = True,
                       clip: float | None = None) -> np.ndarray:
    """Laplacian lighting normalisation.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey levels (any real dtype).
    blur_sigma : float
    log : bool
        Filter ``log(LOG_OFFSET + image)`` rather than the image.
    clip : float, optional
        Clip the result to ``[-clip, clip]``.

    Returns
    -------
    ndarray, shape (H, W), float32
    """
    work = image.astype(np.float32)
    if log:
        # log(I + LOG_OFFSET): dark pixels (lip line, nostrils) would otherwise turn sensor noise into signal
        work = np.log(np.maximum(work, 0.0, out=work) + np.float32(LOG_OFFSET), out=work) * np.float32(64.0)
    if blur_sigma > 0:
        work = cv2.GaussianBlur(work, (0, 0), blur_sigma)
    filtered = cv2.Laplacian(work, cv2.CV_32F, ksize=3)
    if clip is not None:
        np.clip(filtered, -clip, clip, out=filtered)
    return filtered


@dataclass(frozen=True, eq=False)
class NormalisedFrame:
    """One camera image, normalised.

    Attributes
    ----------
    image : ndarray, shape (h, w), float32
        Canonical grey image (pose-normalised, cropped; before lighting normalisation).
    filtered : ndarray, shape (h, w), float32
        After the Laplacian (``image`` itself when the Laplacian is off).
    head2cam : ndarray, shape (4, 4) or None
        Head pose; None without a rig or when the LEDs are lost.
    lost : bool
        The LEDs were not found: ``image`` is the unwarped crop and must not be trusted.
    """

    image: np.ndarray
    filtered: np.ndarray
    head2cam: np.ndarray | None
    lost: bool


def normalise(image: np.ndarray, norm: Normalisation, state: PoseState = PoseState(),
              candidates: np.ndarray | None = None) -> tuple[PoseState, NormalisedFrame]:
    """Pose warp (with a head rig), crop and lighting normalisation of one camera image.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
        ``(W, H)`` must be ``norm.input_size``.
    norm : Normalisation
    state : PoseState
    candidates : ndarray, shape (n, 2), optional
        With a head rig: the image's LED candidates already found (:func:`detect_leds`); None: found here.

    Returns
    -------
    (PoseState, NormalisedFrame)
    """
    gray = _gray(image)
    if (gray.shape[1], gray.shape[0]) != norm.input_size:
        raise ValueError(f"image is {gray.shape[1]}x{gray.shape[0]}, the model expects "
                         f"{norm.input_size[0]}x{norm.input_size[1]}")
    head2cam, lost = None, False
    if norm.head_rig is not None:
        state, head2cam = estimate_head_pose(gray, norm, state, candidates=candidates)
        lost = head2cam is None
        if not lost and norm.pose_warp and norm.surface is not None:
            gray = warp_to_canonical(gray, norm, head2cam)
    x, y, w, h = norm.crop
    canonical = gray[y:y + h, x:x + w].astype(np.float32)
    filtered = lighting_normalise(canonical, norm.blur_sigma, norm.log, norm.clip) if norm.laplacian else canonical
    return state, NormalisedFrame(canonical, filtered, head2cam, lost)

"""Render a calibration board held in front of a calibrated camera.

The board's printed image (OpenCV's own ChArUco image, or a drawn chessboard)
is mapped into the camera by inverse mapping: every output sample pixel is
undistorted to a ray through the exact camera model (distortion included,
pinhole or fisheye), intersected with the board plane and looked up in the
board texture. Samples are supersampled (anti-aliased), then blurred and
given Gaussian noise from the caller's seeded generator, so the same inputs
give the same image bit for bit.
"""

from __future__ import annotations

import time
from functools import lru_cache

import cv2
import numpy as np

from livebridge.calibration.boards import Board, parse_board
from livebridge.calibration.cameras import Camera, CameraGroup, undistort_normalised
from livebridge.capture.frame import Frame
from livebridge.capture.sources import Capabilities, SourceBase
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError
from livebridge.geometry.transforms import apply, look_at

BACKGROUND = 110.0  # grey level behind the board


def render_board_view(board: Board | str, camera: Camera, board2world: np.ndarray, blur_px: float = 0.0,
                      noise: float = 0.0, rng: np.random.Generator | None = None, supersample: int = 3,
                      background: float = BACKGROUND) -> np.ndarray:
    """Grayscale image of ``board`` seen by ``camera``.

    Parameters
    ----------
    board : Board or str
        Board or board spec.
    camera : Camera
        Intrinsics, distortion and ``world2cam`` of the viewing camera (mm).
    board2world : ndarray, shape (4, 4)
        Pose of the board frame (see :mod:`livebridge.calibration.boards`) in the world, mm.
    blur_px : float
        Gaussian blur sigma in output pixels (0: none).
    noise : float
        Standard deviation of additive Gaussian noise in grey levels (0: none).
    rng : numpy.random.Generator, optional
        Source of the noise; required when ``noise > 0``.
    supersample : int
        Samples per pixel along each axis (anti-aliasing).
    background : float
        Grey level where no board is seen.

    Returns
    -------
    ndarray, shape (height, width), uint8
    """
    board = parse_board(board)
    board2world = np.asarray(board2world, dtype=np.float64)
    if board2world.shape != (4, 4):
        raise ValueError(f"board2world must be (4, 4), got {board2world.shape}")
    if noise > 0 and rng is None:
        raise ValueError("noise > 0 needs a seeded rng")
    board2cam = camera.world2cam @ board2world
    rotation, translation = board2cam[:3, :3], board2cam[:3, 3]
    rays = _rays(camera.size, camera.matrix.tobytes(), camera.distortions.tobytes(), camera.fisheye, supersample)

    # Intersect each ray (x, y, 1) with the board plane z_board = 0: in board axes the ray is rays @ R.
    along = rays @ rotation
    offset = rotation.T @ translation
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = offset[2] / along[..., 2]
    visible = np.isfinite(depth) & (depth > 0)
    board_xy = along[..., :2] * depth[..., None] - offset[:2]

    texture, px_per_mm, margin_px = _texture(board, camera, board2cam)
    map_x = (board_xy[..., 0] * px_per_mm + margin_px - 0.5).astype(np.float32)
    map_y = (board_xy[..., 1] * px_per_mm + margin_px - 0.5).astype(np.float32)
    map_x[~visible] = -1e6
    map_y[~visible] = -1e6
    samples = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                        borderValue=float(background))
    width, height = camera.size
    image = samples.reshape(height, supersample, width, supersample).mean(axis=(1, 3))
    if blur_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur_px)
    if noise > 0:
        image = image + rng.normal(0.0, noise, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _texture(board: Board, camera: Camera, board2cam: np.ndarray) -> tuple[np.ndarray, float, int]:
    """Board image at a resolution finer than one output sample, plus its mm->px scale and margin."""
    distance = max(float(np.linalg.norm(board2cam[:3, 3])), 1.0)
    focal = float(camera.matrix[0, 0])
    square_px_in_view = focal * board.square_mm / distance
    px_per_square = int(np.clip(np.ceil(square_px_in_view * 4 / 8) * 8, 32, 400))
    return _board_texture(board, px_per_square) + (px_per_square / board.square_mm,
                                                   int(round(0.5 * px_per_square)))


@lru_cache(maxsize=16)
def _board_texture(board: Board, px_per_square: int) -> tuple[np.ndarray]:
    return (board.image(px_per_square, margin_squares=0.5).astype(np.float32),)


@lru_cache(maxsize=8)
def _rays(size: tuple[int, int], matrix: bytes, distortions: bytes, fisheye: bool, supersample: int) -> np.ndarray:
    """Undistorted normalised rays ``(x, y, 1)`` of every sample, shape (h*s, w*s, 3), cached per camera."""
    width, height = size
    k = np.frombuffer(matrix).reshape(3, 3)
    d = np.frombuffer(distortions)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    u = (np.arange(width)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(height)[:, None] + offsets[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    pixels = np.stack([uu.ravel(), vv.ravel()], axis=1)
    normalised = undistort_normalised(pixels, k, d, fisheye)
    normalised = normalised.reshape(len(v), len(u), 2)
    rays = np.concatenate([normalised, np.ones(normalised.shape[:2] + (1,))], axis=2)
    rays.setflags(write=False)
    return rays


# ---------------------------------------------------------------- synthetic calibration scenes


def example_rig(n_cams: int = 4, size: tuple[int, int] = (800, 600), distance_mm: float = 1000.0,
                fisheye: bool = False, seed: int = 0) -> CameraGroup:
    """Cameras on an arc ``distance_mm`` from the origin, all looking at it (world +y up, +z towards them).

    Each camera gets its own focal length, principal point and lens distortion (seeded).
    """
    rng = np.random.default_rng(seed)
    width, height = size
    cameras = []
    for i, azimuth in enumerate(np.radians(np.linspace(-35, 35, n_cams))):
        elevation = np.radians(rng.uniform(-10, 15))
        center = distance_mm * np.array([np.sin(azimuth) * np.cos(elevation), np.sin(elevation),
                                         np.cos(azimuth) * np.cos(elevation)])
        world2cam = look_at(center, rng.uniform(-40, 40, 3))
        focal = width * rng.uniform(1.0, 1.3)
        matrix = np.array([[focal, 0, width / 2 + rng.uniform(-15, 15)],
                           [0, focal * rng.uniform(0.995, 1.005), height / 2 + rng.uniform(-15, 15)], [0, 0, 1]])
        if fisheye:
            distortions = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.02, 0.02), 0.0, 0.0])
        else:
            distortions = np.array([rng.uniform(-0.25, -0.05), rng.uniform(0.0, 0.12), rng.uniform(-1e-3, 1e-3),
                                    rng.uniform(-1e-3, 1e-3), rng.uniform(-0.02, 0.0)])
        cameras.append(Camera(f"cam{i}", size, matrix, distortions, cv2.Rodrigues(world2cam[:3, :3])[0].ravel(),
                              world2cam[:3, 3], fisheye))
    return CameraGroup(cameras)


def example_board_poses(board: Board | str, n_views: int, seed: int = 0, spread_mm: float = 150.0,
                        tilt_deg: float = 30.0) -> np.ndarray:
    """``board2world`` (n_views, 4, 4): the board held upright facing +z near the origin, varied (seeded)."""
    board = parse_board(board)
    rng = np.random.default_rng(seed)
    centre = np.array([board.size_mm[0] / 2, board.size_mm[1] / 2, 0.0])
    upright = np.diag([1.0, -1.0, -1.0])  # board x = world x, board y = down, board z = into the board
    poses = np.tile(np.eye(4), (n_views, 1, 1))
    for v in range(n_views):
        angles = np.radians(rng.uniform(-1, 1, 3) * np.array([tilt_deg, tilt_deg, 25.0]))
        rotation = cv2.Rodrigues(angles)[0] @ upright
        position = rng.uniform(-1, 1, 3) * np.array([spread_mm, spread_mm * 0.7, spread_mm])
        poses[v, :3, :3] = rotation
        poses[v, :3, 3] = position - rotation @ centre
    return poses


def project_board(board: Board | str, group: CameraGroup, board2world: np.ndarray, noise_px: float = 0.0,
                  rng: np.random.Generator | None = None, min_corners: int | None = None) -> np.ndarray:
    """Synthetic detections without rendering: projected corners plus Gaussian pixel noise.

    Corners behind a camera, outside its image, or on a board seen edge-on or from behind are NaN; views
    with fewer than ``min_corners`` (default ``board.min_corners``) visible corners are all NaN.

    Returns
    -------
    corners : ndarray, shape (n_cams, n_views, n_corners, 2)
    """
    board = parse_board(board)
    minimum = board.min_corners if min_corners is None else min_corners
    n_views = len(board2world)
    out = np.full((len(group), n_views, board.n_corners, 2), np.nan)
    for c, camera in enumerate(group.cameras):
        for v in range(n_views):
            board2cam = camera.world2cam @ board2world[v]
            in_cam = apply(board2cam, board.object_points)
            facing = board2cam[:3, 2] @ board2cam[:3, 3] / np.linalg.norm(board2cam[:3, 3])
            if facing < 0.25 or (in_cam[:, 2] <= 0).any():
                continue
            world = apply(board2world[v], board.object_points)
            pixels = camera.project(world)
            if noise_px > 0:
                pixels = pixels + rng.normal(0.0, noise_px, pixels.shape)
            inside = (pixels[:, 0] >= 0) & (pixels[:, 0] <= camera.size[0] - 1) & \
                (pixels[:, 1] >= 0) & (pixels[:, 1] <= camera.size[1] - 1)
            if board.kind == "chessboard" and not inside.all() or inside.sum() < minimum:
                continue
            out[c, v, inside] = pixels[inside]
    return out


# ---------------------------------------------------------------- a simulated rig filming a board (sim://rig?board=)

BOARD_URL_KEYS = {"board", "cameras", "camera", "views", "seed", "size", "noise", "blur", "frames"}


class BoardSource(SourceBase):
    """One camera of :func:`example_rig` filming a board held still in each of :func:`example_board_poses`.

    Frame ``seq`` shows pose ``seq % views`` (the poses repeat, like someone waving the board around again),
    with noise seeded by ``(seed, camera, seq)``, so every source of one URL but ``camera`` shows the same
    board at the same ``seq``. Unpaced; ``frames=N`` ends the source after N frames.
    """

    def __init__(self, board: Board, group: CameraGroup, camera: int, poses: np.ndarray, seed: int,
                 noise: float, blur_px: float, n_frames: int | None):
        self.board, self.group, self.camera, self.poses = board, group, int(camera), poses
        self.seed, self.noise, self.blur_px, self.n_frames = seed, noise, blur_px, n_frames
        self.source_id = group.cameras[self.camera].name
        self.realtime = False
        self._seq, self._running = 0, False

    def start(self) -> None:
        self._running = True

    def stop(self) -> None:
        self._running = False

    @property
    def calibration(self) -> Camera:
        """The simulated camera (ground truth)."""
        return self.group.cameras[self.camera]

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(size=self.calibration.size)

    def read(self, timeout: float | None = None) -> Frame | None:
        if not self._running:
            raise RuntimeError(f"{self.source_id}: read() before start()")
        if self.n_frames is not None and self._seq >= self.n_frames:
            self._end(None)  # the end of the simulated take, not a fault
            return None
        seq = self._seq
        self._seq += 1
        rng = np.random.default_rng((self.seed, self.camera, seq))
        image = render_board_view(self.board, self.calibration, self.poses[seq % len(self.poses)], self.blur_px,
                                  self.noise, rng, supersample=2)
        return Frame(image=image, t_capture=time.monotonic(), seq=seq, source_id=self.source_id)


def open_board_url(url: DeviceURL) -> list[BoardSource]:
    """Sources of ``sim://rig?board=SPEC&cameras=2&camera=0&views=12&seed=0&size=640x480&noise=2&blur=0.7
    &frames=N``: the cameras of :func:`example_rig` (``cameras``, ``size``, ``seed``) filming the board ``SPEC``
    in ``views`` poses of :func:`example_board_poses` (seed ``seed + 1``); ``camera=i``: only camera ``i`` (one
    source per URL, as ``livebridge calibrate run --sources`` wants)."""
    url.check_known(BOARD_URL_KEYS)
    try:
        board = parse_board(url.query["board"])
    except InputError as error:
        raise InputError(error.message, url.url, "board") from None
    n_cams = url.take("cameras", int, 2, within=(1, 16))
    seed = url.take("seed", int, 0, within=(0, 2**31 - 1))
    size = url.query.get("size", "640x480").lower().split("x")
    if len(size) != 2 or not all(part.isdigit() and 64 <= int(part) <= 4096 for part in size):
        raise InputError("size must look like 640x480 (64..4096 a side)", url.url, "size")
    group = example_rig(n_cams, size=(int(size[0]), int(size[1])), seed=seed)
    poses = example_board_poses(board, url.take("views", int, 12, within=(1, 10_000)), seed=seed + 1)
    options = dict(seed=seed, noise=url.take("noise", float, 2.0, within=(0.0, 100.0)),
                   blur_px=url.take("blur", float, 0.7, within=(0.0, 20.0)),
                   n_frames=url.take("frames", int, None, within=(1, 10**9)))
    camera = url.take("camera", int, None, within=(0, n_cams - 1))
    chosen = range(n_cams) if camera is None else [camera]
    return [BoardSource(board, group, c, poses, **options) for c in chosen]

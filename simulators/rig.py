"""A simulated camera rig: N cameras filming the synthetic performer's markers, with ground truth.

Each camera renders, per frame, the markers as bright anti-aliased discs whose radius follows their
distance (``f * diameter / 2 / depth``) on a dark, faintly shaded face (Lambert shading of the basis'
neutral mesh lit from the camera, as by an IR ring light), rendered once per camera and cached, and
shifted (translated) with the head. A marker is hidden when the face surface lies in front of it (a per-frame depth
splat of the deformed, posed mesh), when it faces away from the camera (more than ``max_view_deg``), or at random
(``occlusion_rate``: a hand, hair, a prop); the first two are the visibility model the marker-layout designer
uses too (:mod:`livebridge.geometry.visibility`).
Sensor noise comes from pre-generated noise tiles read at random offsets; optional motion blur smears
each marker over the exposure, spurious highlights appear on the face, frames drop and timestamps jitter.
Everything is seeded: frame ``seq`` of camera ``c`` depends only on ``(seed, seq, c)`` and the
configuration, not on the order in which cameras are read.

The rig knows the ground truth (:class:`SimTruth`): 3D marker positions, labels, contractions,
``head2world``, per-camera visibility and true pixel positions.

Use it directly (``SimRig(...).framesets(n)`` yields :class:`~livebridge.capture.frame.FrameSet` with
``.truth``) or through the camera-source registry (``sim://rig?cameras=4&seed=1``, read by
:mod:`~livebridge.simulators.rig_url`: one :class:`SimCameraSource` per camera, all sharing one rig). The images
are drawn by :mod:`~livebridge.simulators.drawing`.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from livebridge.calibration.cameras import Camera, CameraGroup
from livebridge.capture.frame import Frame, FrameSet
from livebridge.capture.sources import Capabilities, ExposureSetting, SourceBase
from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.face.meshio import triangle_normals
from livebridge.geometry.transforms import apply, look_at
from livebridge.geometry.visibility import depth_cell_mm, in_view, sees
from livebridge.simulators.drawing import NoiseTiles, render_discs, shaded_face, shift_into

SYNC_MODES = ("hardware", "free")
_EYE = np.eye(4)
_AT_REST = 1e-9 + 1e-5 * _EYE  # np.allclose's tolerance of head2world to the identity


@dataclass(frozen=True)
class RigConfig:
    """How the simulated rig renders and misbehaves. All defaults give a clean, hardware-synced rig.

    Attributes
    ----------
    size : tuple of int
        Image ``(width, height)`` of generated cameras (cameras from a calibration keep their own size).
    fps : float
    distance_mm : tuple of float
        ``(near, far)`` distance of generated cameras from the face centre.
    spread_deg : float
        Horizontal arc the generated cameras span in front of the face.
    fill : float
        Fraction of the image height the face fills in a generated camera (sets the focal length).
    marker_diameter_mm : float
        Physical marker diameter; the disc radius in pixels is ``f * diameter / 2 / depth``.
    marker_level : float
        Marker brightness (0..255) at the nominal exposure.
    face_level : float
        Brightest shading of the face background at the nominal exposure (dark: markers stand out).
    ambient_level : float
        Background level outside the face.
    noise_sigma : float
        Standard deviation of additive sensor noise in grey levels (0: none).
    motion_blur : bool
        Smear each marker over the exposure time along its motion.
    spurious_rate : float
        Expected number of spurious highlights (small bright blobs on the face) per camera frame.
    drop_rate : float
        Probability that a camera drops a frame.
    jitter_s : float
        Standard deviation of timestamp noise (clipped at 3 sigma), seconds.
    sync : {"hardware", "free"}
        ``hardware``: all cameras share one sync domain and frame counter, exposures start together;
        ``free``: each camera runs on its own (own domain, own counter, a fixed time offset of up to
        ``free_offset`` frame periods).
    free_offset : float
        Largest per-camera time offset of a free-running camera, in frame periods.
    occlusion : bool
        Hide markers behind the face surface (depth test).
    max_view_deg : float
        Markers whose normal is more than this angle from the direction to the camera are hidden.
    occlusion_rate : float
        Probability that a marker view that would otherwise be visible is hidden (a hand, hair, a prop),
        independently per marker and camera, seeded by ``(seed, seq, camera)``.
    exposure_us : float
        Nominal exposure; brightness scales with ``exposure * gain`` relative to it.
    follow_head : bool
        Shift the cached face background with the head (whole-pixel image translation of the face centre).
    buffers : int
        Frames a paced (``realtime``) simulated camera driver holds. A reader that falls behind never gets a
        backlog: it takes the oldest frame still among the newest ``buffers`` that another camera of the rig
        already took (so a busy host still gets frames of one instant from every camera, as from a
        synchronised grabber), or else the newest frame whose exposure has ended.
    """

    size: tuple[int, int] = (1280, 800)
    fps: float = 60.0
    distance_mm: tuple[float, float] = (600.0, 800.0)
    spread_deg: float = 80.0
    fill: float = 0.75
    marker_diameter_mm: float = 3.0
    marker_level: float = 230.0
    face_level: float = 40.0
    ambient_level: float = 6.0
    noise_sigma: float = 2.0
    motion_blur: bool = False
    spurious_rate: float = 0.0
    drop_rate: float = 0.0
    jitter_s: float = 0.0
    sync: str = "hardware"
    free_offset: float = 0.15
    occlusion: bool = True
    max_view_deg: float = 80.0
    occlusion_rate: float = 0.0
    exposure_us: float = 2000.0
    follow_head: bool = True
    buffers: int = 3

    def __post_init__(self):
        if self.sync not in SYNC_MODES:
            raise InputError(f"sync must be one of {SYNC_MODES}, got {self.sync!r}", field="sync")
        if (not isinstance(self.size, tuple) or len(self.size) != 2
                or not all(isinstance(v, int | np.integer) and SIZE_RANGE[0] <= v <= SIZE_RANGE[1] for v in self.size)):
            raise InputError(f"size must be (width, height), each an integer in {SIZE_RANGE[0]}..{SIZE_RANGE[1]}, "
                             f"got {self.size}", field="size")
        near, far = self.distance_mm
        if not (math.isfinite(near) and math.isfinite(far) and 0 < near <= far):
            raise InputError(f"distance_mm must be (near, far) with 0 < near <= far, got {self.distance_mm}",
                             field="distance_mm")
        for name, (low, high, open_low, open_high) in _CONFIG_RANGES.items():
            check_range(name, getattr(self, name), low, high, open_low, open_high)
        if not 1 <= self.buffers <= 64:
            raise InputError(f"buffers must be in 1..64, got {self.buffers}", field="buffers")


SIZE_RANGE = (16, 4096)  # pixels, each of width and height
MAX_CAMERAS = 16
PAIR_SPREAD_DEG = 30.0  # a rig of two cameras: both see nearly every marker (80 deg apart they share a third)
MAX_SEED = 2**32 - 1
_CONFIG_RANGES = {  # field: (low, high, low excluded, high excluded)
    "fps": (1.0, 1000.0, False, False),
    "spread_deg": (0.0, 360.0, False, False),
    "fill": (0.0, 1.0, True, False),
    "marker_diameter_mm": (0.0, 50.0, True, False),
    "marker_level": (0.0, 255.0, False, False),
    "face_level": (0.0, 255.0, False, False),
    "ambient_level": (0.0, 255.0, False, False),
    "noise_sigma": (0.0, 255.0, False, False),
    "spurious_rate": (0.0, 100.0, False, False),
    "drop_rate": (0.0, 1.0, False, True),
    "jitter_s": (0.0, 1.0, False, False),
    "free_offset": (0.0, 1.0, False, False),
    "max_view_deg": (0.0, 180.0, False, False),
    "occlusion_rate": (0.0, 1.0, False, True),
    "exposure_us": (0.0, 1e6, True, False),
}


def check_range(name: str, value, low: float, high: float, open_low: bool, open_high: bool) -> None:
    """Raise :class:`InputError` naming ``name`` and its range unless ``value`` is a finite number in it."""
    ok = isinstance(value, int | float | np.number) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (low < value if open_low else low <= value) and (value < high if open_high else value <= high)
    if not ok:
        interval = f"{'(' if open_low else '['}{low:g}, {high:g}{')' if open_high else ']'}"
        raise InputError(f"{name} must be a finite number in {interval}, got {value!r}", field=name)


@dataclass(frozen=True, eq=False)
class SimTruth:
    """Ground truth of one simulated instant.

    Attributes
    ----------
    seq : int
        Frame number of the performer (and of a hardware-synced rig).
    t : float
        Performance time, seconds from the start.
    marker_names : tuple of str, length n_markers
    points_3d : ndarray, shape (n_markers, 3)
        Marker centres in the world frame, mm.
    contractions : ndarray, shape (n_muscles,)
    head2world : ndarray, shape (4, 4)
    visible : ndarray of bool, shape (n_cams, n_markers)
        Drawn in that camera's image (False also where the camera dropped the frame).
    points_2d : ndarray, shape (n_cams, n_markers, 2)
        True (distorted) pixel position of each marker centre; NaN where not visible.
    radius_px : ndarray, shape (n_cams, n_markers)
        Drawn disc radius in pixels; NaN where not visible.
    spurious_2d : tuple of ndarray, length n_cams, each shape (n_spurious, 2)
        Pixel positions of the spurious highlights drawn in each camera.
    dropped : ndarray of bool, shape (n_cams,)
        Cameras that dropped this frame.
    """

    seq: int
    t: float
    marker_names: tuple[str, ...]
    points_3d: np.ndarray
    contractions: np.ndarray
    head2world: np.ndarray
    visible: np.ndarray
    points_2d: np.ndarray
    radius_px: np.ndarray
    spurious_2d: tuple[np.ndarray, ...]
    dropped: np.ndarray


# ------------------------------------------------------------------------------------------ set-up helpers

def face_centre(basis: Basis) -> np.ndarray:
    """Centre of the neutral face's bounding box, mm, shape (3,)."""
    return 0.5 * (basis.neutral.min(axis=0) + basis.neutral.max(axis=0))


def generate_cameras(basis: Basis, n_cameras: int = 4, config: RigConfig | None = None,
                     seed: int = 0) -> CameraGroup:
    """Cameras on an arc in front of the face (+z), looking at its centre, at 0.5–1 m.

    Azimuths spread evenly over ``config.spread_deg`` (two cameras: at most :data:`PAIR_SPREAD_DEG` apart,
    since every marker must then be seen by both); elevations alternate a little above and below;
    distances are drawn in ``config.distance_mm``; the focal length makes the face fill ``config.fill``
    of the image height. No lens distortion.

    Returns
    -------
    CameraGroup
        Cameras ``cam0 .. cam{n-1}``, image size ``config.size``.
    """
    config = config or RigConfig()
    if n_cameras < 1:
        raise InputError(f"need at least one camera, got {n_cameras}", field="cameras")
    rng = np.random.default_rng([int(seed), 5])
    spread = min(config.spread_deg, PAIR_SPREAD_DEG) if n_cameras == 2 else config.spread_deg
    azimuths = np.deg2rad(np.linspace(-0.5, 0.5, n_cameras) * spread) if n_cameras > 1 else [0.0]
    cameras = []
    for k, azimuth in enumerate(azimuths):
        elevation = np.deg2rad(8.0 if k % 2 == 0 else -6.0) if n_cameras > 1 else 0.0
        cameras.append(face_camera(basis, f"cam{k}", azimuth, elevation, rng.uniform(*config.distance_mm), config))
    return CameraGroup(cameras)


def face_camera(basis: Basis, name: str, azimuth: float, elevation: float, distance: float,
                config: RigConfig | None = None, distortion: np.ndarray | None = None) -> Camera:
    """A camera ``distance`` mm from the face centre, at ``azimuth`` / ``elevation`` (radians) from the face's
    +z, looking at the centre, its focal length making the face fill ``config.fill`` of the image height.

    ``distortion``: OpenCV coefficients ``(5,)`` (default none).
    """
    config = config or RigConfig()
    target = face_centre(basis)
    width, height = config.size
    direction = np.array([np.sin(azimuth) * np.cos(elevation), np.sin(elevation),
                          np.cos(azimuth) * np.cos(elevation)])
    world2cam = look_at(target + distance * direction, target)
    focal = config.fill * height * distance / float(np.ptp(basis.neutral[:, 1]))
    matrix = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]])
    return Camera(name, (width, height), matrix, np.zeros(5) if distortion is None else np.asarray(distortion),
                  cv2.Rodrigues(world2cam[:3, :3])[0].ravel(), world2cam[:3, 3])


def generate_markers(basis: Basis, n_face: int = 40, n_head: int = 4, seed: int = 0) -> MarkerSet:
    """A spread-out development marker set: face markers by farthest-point sampling of front-facing vertices,
    head markers at the top and the temples.

    Returns
    -------
    MarkerSet
        ``n_face`` face markers (``f00..``; upper/lower by height relative to the nose) and ``n_head`` head
        markers (``h0..``).
    """
    rng = np.random.default_rng([int(seed), 7])
    vertices, triangles = basis.neutral, basis.triangles
    normals = triangle_normals(vertices, triangles)
    centroids = vertices[triangles].mean(axis=1)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    front = (normals[:, 2] > 0.5) & (centroids[:, 2] > low[2] + 0.45 * (high[2] - low[2]))
    candidates = np.flatnonzero(front)
    if len(candidates) < n_face + n_head:
        raise InputError(f"the mesh has only {len(candidates)} front-facing triangles for {n_face + n_head} markers")
    chosen = [int(rng.choice(candidates))]
    distance = np.linalg.norm(centroids[candidates] - centroids[chosen[0]], axis=1)
    for _ in range(n_face + n_head - 1):
        chosen.append(int(candidates[np.argmax(distance)]))
        distance = np.minimum(distance, np.linalg.norm(centroids[candidates] - centroids[chosen[-1]], axis=1))
    chosen = np.array(chosen)
    # head markers: the highest of the chosen (forehead top, temples) are rigid-rig markers
    order = np.argsort(-centroids[chosen, 1])
    head, face = chosen[order[:n_head]], chosen[order[n_head:]]
    nose_y = vertices[np.argmax(vertices[:, 2]), 1]
    names, regions, roles = [], [], []
    for k, tri in enumerate(face):
        names.append(f"f{k:02d}")
        regions.append("upper" if centroids[tri, 1] > nose_y else "lower")
        roles.append("face")
    for k, _ in enumerate(head):
        names.append(f"h{k}")
        regions.append("upper")
        roles.append("head")
    all_triangles = np.concatenate([face, head])
    barycentric = rng.dirichlet(np.full(3, 4.0), size=len(all_triangles))
    return MarkerSet(tuple(names), all_triangles, barycentric, tuple(regions), tuple(roles))


def default_face() -> tuple[Basis, MarkerSet]:
    """The built-in face and its designed markers (``sim://rig?basis=PATH.npz`` films another face)."""
    from livebridge.face.builtin import builtin_basis, builtin_markers

    return builtin_basis(), builtin_markers()


@dataclass(frozen=True, eq=False)
class _State:
    """Per-seq world state shared by the cameras."""

    seq: int
    t: float
    contractions: np.ndarray
    head2world: np.ndarray
    markers: np.ndarray  # (n, 3) world
    previous: np.ndarray  # (n, 3) world, one frame earlier (motion blur)
    vertices: np.ndarray | None  # (V, 3) world, deformed and posed (None when not needed)
    normals: np.ndarray  # (n, 3) marker normals, world
    anchor: np.ndarray | None  # (1, 3) world face centre, when the background follows a moved head


# --------------------------------------------------------------------------------------------------- rig

class SimRig:
    """N simulated cameras filming a synthetic performer.

    Parameters
    ----------
    basis : Basis
        The face (mm, +y up, +z out of the face).
    markers : MarkerSet
    cameras : CameraGroup, optional
        Calibrated cameras in the world (= model-at-rest) frame; default: :func:`generate_cameras`.
    n_cameras : int
        Number of generated cameras when ``cameras`` is None.
    config : RigConfig
    seed : int
        Seeds the performer, the generated cameras and all noise.
    performer : object, optional
        Anything with ``frames()`` yielding frames with ``seq, t, contractions, head2world,
        marker_positions``; default: :class:`livebridge.simulators.performer.Performer` with ``script``.
    script : str
        Performer script when ``performer`` is None.
    """

    def __init__(self, basis: Basis, markers: MarkerSet, cameras: CameraGroup | None = None, n_cameras: int = 4,
                 config: RigConfig | None = None, seed: int = 0, performer=None, script: str = "mixed"):
        self.config = config or RigConfig()
        self.seed = int(seed)
        self.basis, self.markers = basis, markers
        markers.check_mesh(len(basis.triangles))
        self.cameras = cameras if cameras is not None else generate_cameras(basis, n_cameras, self.config, seed)
        if performer is None:
            from livebridge.simulators.performer import Performer

            performer = Performer(basis, markers, fps=self.config.fps, seed=seed, script=script, realtime=False)
        self._performer = performer
        self._frames_iter = None
        self._next_seq = 0
        self._states: OrderedDict[int, _State] = OrderedDict()
        self._performed: OrderedDict = OrderedDict()  # recent performer frames by seq (cheap to keep)
        self._taken: deque[int] = deque(maxlen=64)  # recent frames paced cameras have taken, ascending
        self._lock = threading.RLock()
        self._window = 256
        n_cams = len(self.cameras)
        self.t0: float | None = None
        rng = np.random.default_rng([self.seed, 17])
        if self.config.sync == "free":
            period = 1.0 / self.config.fps
            self._offsets = rng.uniform(-1, 1, size=n_cams) * self.config.free_offset * period
            self._seq_offsets = rng.integers(0, 10_000, size=n_cams)
            self.sync_domains = tuple(f"sim{self.seed}:{c.name}" for c in self.cameras.cameras)
        else:
            self._offsets = np.zeros(n_cams)
            self._seq_offsets = np.zeros(n_cams, dtype=np.int64)
            self.sync_domains = (f"sim{self.seed}:rig",) * n_cams
        self._exposure = [(self.config.exposure_us, 1.0)] * n_cams
        self._noise = [NoiseTiles(c.size, self.config.noise_sigma, self.seed * 1000 + k)
                       if self.config.noise_sigma > 0 else None for k, c in enumerate(self.cameras.cameras)]
        # cached backgrounds: float32 at nominal brightness, then uint8 per brightness scale
        self._backgrounds = [None] * n_cams
        self._scaled: dict[tuple[int, float], np.ndarray] = {}
        self._marker_triangles = basis.triangles[markers.triangles]  # (n, 3) vertex indices
        self._elements = basis.elements.reshape(len(basis.elements), -1)  # (M, V*3)
        self._anchor = face_centre(basis)
        self._anchor_pixels = [camera.project(self._anchor[None])[0] for camera in self.cameras.cameras]
        self._world2cam = [camera.world2cam for camera in self.cameras.cameras]
        self._centers = [camera.center for camera in self.cameras.cameras]
        self._cell_mm = depth_cell_mm(basis.neutral, basis.triangles)

    # ----------------------------------------------------------------------------- public API
    @property
    def names(self) -> tuple[str, ...]:
        """Camera names (the ``source_id`` of each camera's frames)."""
        return self.cameras.names

    @property
    def n_cameras(self) -> int:
        return len(self.cameras)

    @property
    def period(self) -> float:
        return 1.0 / self.config.fps

    def start(self, t0: float | None = None) -> None:
        """Render the cached backgrounds and fix the host time of frame 0 (``time.monotonic()`` now, unless
        given); idempotent."""
        with self._lock:
            if self.t0 is None:
                for c in range(self.n_cameras):  # the cached backgrounds, before the clock starts
                    self._background(c, 1.0)
                self.t0 = time.monotonic() if t0 is None else float(t0)

    def framesets(self, n: int | None = None, realtime: bool = False, start: int = 0) -> Iterator[FrameSet]:
        """Frame sets with ground truth (``.truth`` is a :class:`SimTruth`), in camera order.

        Parameters
        ----------
        n : int, optional
            How many (default: forever).
        realtime : bool
            Pace frame ``seq`` to host time ``t0 + seq / fps``; False: as fast as the CPU allows.
        start : int
            First performer frame.
        """
        self.start()
        seq = start
        while n is None or seq < start + n:
            if realtime:
                delay = self.t0 + seq * self.period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            frames, truth = self.render(seq)
            yield FrameSet.from_frames(frames, self.names, index=seq, truth=truth)
            seq += 1

    def render(self, seq: int, cameras=None) -> tuple[list[Frame | None], SimTruth]:
        """Render frame ``seq`` of every camera (or the camera indices in ``cameras``).

        Returns
        -------
        frames : list of (Frame or None), length n_cams
            None for a dropped frame or a camera not asked for.
        truth : SimTruth
        """
        return self._film(seq, cameras, self._render_camera)

    def truth(self, seq: int) -> SimTruth:
        """Ground truth of frame ``seq`` without drawing images (spurious highlights are left out)."""
        return self._film(seq, None, self._see_camera)[1]

    def _film(self, seq: int, cameras, film_camera) -> tuple[list[Frame | None], SimTruth]:
        """Frame ``seq`` of the cameras ``cameras`` (None: all), each filmed by ``film_camera(state, c)``
        (:meth:`_render_camera`, or :meth:`_see_camera` for the ground truth only)."""
        self.start()
        state = self._state(seq)
        indices = range(self.n_cameras) if cameras is None else cameras
        n_cams, n_markers = self.n_cameras, len(self.markers)
        visible = np.zeros((n_cams, n_markers), dtype=bool)
        points_2d = np.full((n_cams, n_markers, 2), np.nan)
        radius = np.full((n_cams, n_markers), np.nan)
        spurious = [np.zeros((0, 2))] * n_cams
        dropped = np.zeros(n_cams, dtype=bool)
        frames: list[Frame | None] = [None] * n_cams
        for c in indices:
            frame, vis, pix, rad, spur, drop = film_camera(state, c)
            frames[c], spurious[c], dropped[c] = frame, spur, drop
            visible[c], points_2d[c], radius[c] = vis, np.where(vis[:, None], pix, np.nan), np.where(vis, rad, np.nan)
        truth = SimTruth(seq, state.t, self.markers.names, state.markers, state.contractions, state.head2world,
                         visible, points_2d, radius, tuple(spurious), dropped)
        return frames, truth

    def camera_frame(self, seq: int, camera: int) -> Frame | None:
        """Frame ``seq`` of one camera, None when that camera drops it."""
        return self.render(seq, cameras=[camera])[0][camera]

    def source_seq(self, seq: int, camera: int) -> int:
        """The frame counter camera ``camera`` stamps on rig frame ``seq``."""
        return int(seq + self._seq_offsets[camera])

    def set_exposure(self, camera: int, exposure_us: float, gain: float) -> ExposureSetting:
        """Set one camera's exposure (brightness scales with ``exposure * gain``); returns what was applied."""
        exposure_us = float(np.clip(exposure_us, 10.0, 0.9e6 / self.config.fps))
        gain = float(np.clip(gain, 1.0, 16.0))
        with self._lock:
            self._exposure[camera] = (exposure_us, gain)
        return ExposureSetting(True, exposure_us, gain)

    def ready_time(self, seq: int, camera: int) -> float:
        """Host monotonic time at which frame ``seq`` of camera ``camera`` has been exposed (end of exposure
        window of a frame period centred on its capture time)."""
        self.start()
        return self.t0 + (seq + 0.5) * self.period + float(self._offsets[camera])

    def due_seq(self, now: float, camera: int) -> int:
        """The newest frame of camera ``camera`` fully exposed at host time ``now`` (-1 before the first)."""
        self.start()
        return int(math.floor((now - self.t0 - float(self._offsets[camera])) / self.period - 0.5))

    def grab(self, next_seq: int, due: int) -> int:
        """The frame a late reader takes (see ``RigConfig.buffers``): the oldest frame another camera took that
        is still buffered (not older than ``due - buffers + 1``) and not before ``next_seq``, else ``due``."""
        with self._lock:
            low = max(next_seq, due - self.config.buffers + 1)
            candidates = [seq for seq in self._taken if low <= seq <= due]
            if candidates:
                return candidates[0]
            self._took(due)
            return due

    def _took(self, seq: int) -> None:
        """Remember the frames cameras of the rig have taken (late readers align to them)."""
        with self._lock:
            if not self._taken or seq > self._taken[-1]:
                self._taken.append(seq)

    def sources(self, realtime: bool = True) -> list[SimCameraSource]:
        """One camera source per camera, sharing this rig."""
        return [SimCameraSource(self, k, realtime) for k in range(self.n_cameras)]

    def render_board(self, board, board2world: np.ndarray, blur_px: float = 0.0, noise: float | None = None,
                     seed: int = 0) -> list[np.ndarray]:
        """Images of a calibration board held in front of the rig, one per camera.

        Uses :func:`livebridge.simulators.board_render.render_board_view`.

        Parameters
        ----------
        board : the calibration board (ChArUco or chessboard) of :mod:`livebridge.calibration`
        board2world : ndarray, shape (4, 4)
        blur_px, noise : float
            Gaussian blur (pixels) and noise (grey levels); ``noise`` defaults to ``config.noise_sigma``.

        Returns
        -------
        list of ndarray of uint8, shape (height, width)
        """
        from livebridge.simulators.board_render import render_board_view

        noise = self.config.noise_sigma if noise is None else noise
        rng = np.random.default_rng([self.seed, int(seed), 23])
        return [render_board_view(board, camera, board2world, blur_px, noise, rng) for camera in self.cameras.cameras]

    # ----------------------------------------------------------------------------- internals
    def _state(self, seq: int) -> _State:
        with self._lock:
            state = self._states.get(seq)
            if state is not None:
                return state
            frame = self._performed.get(seq)
            if frame is None:
                if seq < self._next_seq:
                    self._frames_iter = None  # evicted: restart the deterministic performer from 0
                if self._frames_iter is None:
                    self._frames_iter = iter(self._performer.frames())
                    self._next_seq = 0
                    self._performed.clear()
                while self._next_seq <= seq:
                    performed = next(self._frames_iter)
                    self._next_seq += 1
                    self._performed[performed.seq] = performed
                    while len(self._performed) > 2 * self._window:
                        self._performed.popitem(last=False)
                frame = self._performed[seq]
            previous = self._performed.get(seq - 1, frame)
            state = self._states[seq] = self._make_state(frame, previous.marker_positions)
            while len(self._states) > self._window:
                self._states.popitem(last=False)
            return state

    def _make_state(self, frame, previous: np.ndarray) -> _State:
        contractions = np.asarray(frame.contractions, dtype=np.float64)
        head2world = np.asarray(frame.head2world, dtype=np.float64)
        model = self.basis.neutral + (contractions @ self._elements).reshape(-1, 3)
        vertices = apply(head2world, model)
        normal = triangle_normals(vertices, self._marker_triangles)  # (n, 3)
        # np.allclose(head2world, eye, atol=1e-9) written out: it costs 60 us
        moved = self.config.follow_head and not (np.abs(head2world - _EYE) <= _AT_REST).all()
        return _State(int(frame.seq), float(frame.t), contractions, head2world,
                      np.asarray(frame.marker_positions, dtype=np.float64), np.asarray(previous, dtype=np.float64),
                      vertices if self.config.occlusion else None, normal,
                      apply(head2world, self._anchor[None]) if moved else None)

    def _background(self, c: int, scale: float) -> np.ndarray:
        key = (c, round(scale, 3))
        image = self._scaled.get(key)
        if image is None:
            with self._lock:
                if self._backgrounds[c] is None:
                    self._backgrounds[c] = shaded_face(self.cameras.cameras[c], self.basis.neutral,
                                                        self.basis.triangles, self.config.face_level,
                                                        self.config.ambient_level)
                image = np.clip(self._backgrounds[c] * scale + 0.5, 0, 255).astype(np.uint8)
                self._scaled[key] = image
        return image

    def _visibility(self, c: int, state: _State, pixels: np.ndarray, marker_cam: np.ndarray) -> np.ndarray:
        """Markers facing camera ``c``, inside its image and not behind the face surface, shape (n,) bool.

        Parameters
        ----------
        pixels : ndarray, shape (n, 2)
        marker_cam : ndarray, shape (n, 3)
            The markers in the camera frame.
        """
        to_camera = self._centers[c] - state.markers
        cosine = np.einsum("nd,nd->n", state.normals, to_camera) / np.linalg.norm(to_camera, axis=1)
        cos_limit = math.cos(math.radians(self.config.max_view_deg))
        size = self.cameras.cameras[c].size
        if not self.config.occlusion:
            return in_view(cosine, marker_cam[:, 2], pixels, size, cos_limit)
        return sees(marker_cam, cosine, pixels, size, cos_limit, apply(self._world2cam[c], state.vertices),
                    self._cell_mm)

    def _unoccluded(self, seq: int, c: int) -> np.ndarray:
        """Marker views of camera ``c`` in frame ``seq`` that ``occlusion_rate`` leaves alone, shape (n,) bool.

        One draw per marker from a stream of its own, so what is hidden depends only on ``(seed, seq, c)``: not
        on which other markers are visible, on the other random draws, or on the order cameras are read."""
        rng = np.random.default_rng([self.seed, seq, c, 31])
        return rng.random(len(self.markers)) >= self.config.occlusion_rate

    def _see(self, state: _State, c: int):
        """What camera ``c`` sees of ``state``, before drawing: ``(visible (n,) bool, pixels (n, 2), radii (n,),
        dropped, background shift, rng)``; ``rng`` goes on to draw the image."""
        camera = self.cameras.cameras[c]
        config = self.config
        rng = np.random.default_rng([self.seed, state.seq, c, 29])
        pixels, shift = self._project(c, state)
        marker_cam = apply(self._world2cam[c], state.markers)
        radii = float(camera.matrix[0, 0]) * config.marker_diameter_mm / 2.0 / np.maximum(marker_cam[:, 2], 1e-6)
        if config.drop_rate > 0 and rng.random() < config.drop_rate:
            return np.zeros(len(self.markers), bool), pixels, radii, True, shift, rng
        visible = self._visibility(c, state, pixels, marker_cam)
        if config.occlusion_rate > 0:
            visible &= self._unoccluded(state.seq, c)
        return visible, pixels, radii, False, shift, rng

    def _see_camera(self, state: _State, c: int):
        """:meth:`_render_camera`'s result without the image (frame None, no spurious highlights)."""
        visible, pixels, radii, dropped, _, _ = self._see(state, c)
        return None, visible, pixels, radii, np.zeros((0, 2)), dropped

    def _render_camera(self, state: _State, c: int):
        """``(frame or None, visible, pixels, radii, spurious (n_spurious, 2), dropped)`` of camera ``c``."""
        visible, pixels, radii, dropped, shift, rng = self._see(state, c)
        if dropped:
            return None, visible, pixels, radii, np.zeros((0, 2)), True
        camera, config = self.cameras.cameras[c], self.config
        exposure_us, gain = self._exposure[c]
        image, spurious = self._image(c, state, rng, np.flatnonzero(visible), pixels, radii, shift, (exposure_us, gain))
        t_capture = self.t0 + state.seq * self.period + self._offsets[c]
        if config.jitter_s > 0:
            t_capture += float(np.clip(rng.normal(0.0, config.jitter_s), -3 * config.jitter_s, 3 * config.jitter_s))
        frame = Frame(image, t_capture, self.source_seq(state.seq, c), camera.name, exposure_us, gain,
                      self.sync_domains[c])
        return frame, visible, pixels, radii, spurious, False

    def _project(self, c: int, state: _State) -> tuple[np.ndarray, tuple[int, int]]:
        """Marker pixels in camera ``c``, shape (n, 2), and the whole-pixel shift ``(dx, dy)`` of the cached
        background that follows the head.

        The background only translates with the image motion of the face centre (the head turns by a few
        degrees at most): as cheap as a copy, and the faint background is not what anyone measures.
        """
        camera = self.cameras.cameras[c]
        if state.anchor is None:
            return camera.project(state.markers), (0, 0)
        # one projection call for the markers and the face centre (cv2 projects each point on its own)
        projected = camera.project(np.concatenate([state.markers, state.anchor]))
        shift = projected[-1] - self._anchor_pixels[c]
        if not np.isfinite(shift).all():
            return projected[:-1], (0, 0)
        dx, dy = (int(v) for v in np.rint(shift))
        return projected[:-1], (dx, dy)

    def _image(self, c: int, state: _State, rng: np.random.Generator, index: np.ndarray, pixels: np.ndarray,
               radii: np.ndarray, shift: tuple[int, int], exposure: tuple[float, float]) -> tuple[np.ndarray, ...]:
        """Camera ``c``'s image: the cached background shifted by ``shift``, spurious highlights, the markers
        ``index`` and sensor noise (random draws from ``rng`` in that order).

        Parameters
        ----------
        index : ndarray of int, shape (n_visible,)
        pixels : ndarray, shape (n, 2)
        radii : ndarray, shape (n,)

        Returns
        -------
        image : ndarray of uint8, shape (height, width)
        spurious : ndarray, shape (n_spurious, 2)
            Centres of the spurious highlights.
        """
        config = self.config
        exposure_us, gain = exposure
        scale = exposure_us / config.exposure_us * gain
        background = self._background(c, scale)
        image = np.empty_like(background)
        shift_into(image, background, *shift, int(round(config.ambient_level)))
        spurious = self._spurious(image, c, state, rng)
        if len(index):
            render_discs(image, self._marker_centers(c, state, index, pixels, exposure_us), radii[index],
                         np.full(len(index), min(255.0, config.marker_level * scale)))
        if self._noise[c] is not None:
            self._noise[c].apply(image, rng)
        return image, spurious

    def _spurious(self, image: np.ndarray, c: int, state: _State, rng: np.random.Generator) -> np.ndarray:
        """Draw spurious highlights, small bright blobs on face vertices, into camera ``c``'s ``image``;
        returns their centres, shape (n_spurious, 2)."""
        config = self.config
        count = int(rng.poisson(config.spurious_rate)) if config.spurious_rate > 0 else 0
        if not count:
            return np.zeros((0, 2))
        pick = rng.integers(0, len(self.basis.neutral), size=count)
        spurious = self.cameras.cameras[c].project(apply(state.head2world, self.basis.neutral[pick]))
        spurious = spurious[np.isfinite(spurious).all(axis=1)]
        render_discs(image, spurious, rng.uniform(0.8, 2.5, size=len(spurious)),
                     np.minimum(255.0, rng.uniform(0.5, 1.1, size=len(spurious)) * config.marker_level))
        return spurious

    def _marker_centers(self, c: int, state: _State, index: np.ndarray, pixels: np.ndarray,
                        exposure_us: float) -> np.ndarray:
        """Centres of the markers ``index`` in camera ``c``, shape (n_index, 2); with motion blur, their
        positions over the exposure, shape (n_index, 7, 2)."""
        centers = pixels[index]
        if not self.config.motion_blur:
            return centers
        previous = self.cameras.cameras[c].project(state.previous[index])
        fraction = exposure_us * 1e-6 * self.config.fps  # exposure as a fraction of the frame period
        steps = np.linspace(-0.5, 0.5, 7)[None, :, None]
        return centers[:, None, :] + steps * fraction * (centers - previous)[:, None, :]


# -------------------------------------------------------------------------------------------- sources

class SimCameraSource(SourceBase):
    """One camera of a :class:`SimRig` as a camera source.

    Unpaced (``realtime=False``): every frame, in order, as fast as the reader asks. Paced (``realtime``)
    like a real camera driver: a frame is delivered no earlier than the end of its exposure on the host
    clock, and a reader that falls behind never works through a backlog -- it skips to the newest frame
    that is due, or to a still buffered one another camera took (see ``RigConfig.buffers``); the skipped
    frames are counted in ``skipped``. Frames the
    simulated sensor drops (``RigConfig.drop_rate``) are counted in ``dropped``.
    """

    def __init__(self, rig: SimRig, camera: int, realtime: bool = True):
        self.rig, self.camera, self.realtime = rig, int(camera), realtime
        self.source_id = rig.names[self.camera]
        self._seq = 0
        self._running = False
        self._stop_at: int | None = None
        self.n_frames: int | None = None  # the take ends (cleanly) after this many rig frames
        self.skipped = 0
        self.dropped = 0
        self.delivered = 0

    def start(self) -> None:
        self.rig.start()
        self._running = True

    def stop(self) -> None:
        self._running = False
        self._end(None)

    def kill_after(self, seq: int) -> None:
        """Simulate a camera that stops delivering after rig frame ``seq`` (unplugged)."""
        self._stop_at = int(seq)

    def read(self, timeout: float | None = None) -> Frame | None:
        if not self._running:
            if self._ended:
                return None
            raise RuntimeError(f"{self.source_id}: read() before start()")
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            seq = self._seq
            if self.realtime:
                now = time.monotonic()
                due = self.rig.due_seq(now, self.camera)
                if due > seq:  # the reader is late: no backlog, skip ahead (see RigConfig.buffers)
                    taken = self.rig.grab(seq, due)
                    self.skipped += taken - seq
                    seq = taken
                else:
                    ready = self.rig.ready_time(seq, self.camera)
                    if deadline is not None and ready > deadline:
                        time.sleep(max(0.0, deadline - now))
                        return None
                    if ready > now:
                        time.sleep(ready - now)
                    self.rig._took(seq)
            if self.n_frames is not None and seq >= self.n_frames:
                self._end(None)  # the end of the simulated take, not a fault
                return None
            if self._stop_at is not None and seq > self._stop_at:
                self._end(f"{self.source_id}: camera stopped delivering after frame {self._stop_at} (simulated)")
                return None
            self._seq = seq + 1
            frame = self.rig.camera_frame(seq, self.camera)
            if frame is not None:
                self.delivered += 1
                return frame
            self.dropped += 1

    def set_exposure(self, manual: bool, exposure_us: float | None = None, gain: float | None = None):
        current_exposure, current_gain = self.rig._exposure[self.camera]
        return self.rig.set_exposure(self.camera, current_exposure if exposure_us is None else exposure_us,
                                     current_gain if gain is None else gain)

    @property
    def calibration(self) -> Camera:
        """The simulated camera: the rig films with it."""
        return self.rig.cameras.cameras[self.camera]

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(size=self.rig.cameras.cameras[self.camera].size, fps=self.rig.config.fps,
                            manual_exposure=True, exposure_range_us=(10.0, 0.9e6 / self.rig.config.fps),
                            gain_range=(1.0, 16.0), hardware_sync=self.rig.config.sync == "hardware",
                            formats=("GREY",))

"""A face-video simulator: one camera filming a shaded, textured face with an LED head rig, with ground truth.

The markerless method (CoArt) learns from images of the face, so it is measured against this renderer.
Per frame the face is deformed by the actuation basis (``E0 + sum x_i e_i``), moved rigidly by the head
pose, and drawn by a compiled z-buffer rasteriser (:mod:`~livebridge.simulators.raster`) with per-vertex
normals, Lambert diffuse and a Blinn-Phong highlight from one directional light plus ambient light, on a
procedural skin texture fixed to the neutral face (:mod:`~livebridge.simulators.skin`: the texture moves
and stretches with the skin, and wrinkles appear where it is compressed). The light's intensity and
direction may drift smoothly during a take (``light_drift``); ``exposure`` scales the image; sensor noise is
added last. The head rig (:mod:`~livebridge.simulators.head_rig`) is a dark glasses frame carrying four
bright LEDs, drawn only where nothing on the face is in front of them and while they face the camera.

The camera looks at the face from the front (+z), from ``distance_mm``, its focal length making the face
(hairline to chin) fill ``fill`` of the image height; it has no lens distortion, and :meth:`FaceVideo.camera`
returns it as a :class:`~livebridge.calibration.cameras.Camera`. The world frame is the model frame at
rest: ``head_pose`` (head -> world) is the identity at ``t = 0``.

Everything is a deterministic function of the configuration and the frame number: frame ``seq`` is
the same whether it is rendered alone (:meth:`FaceVideo.frame`) or in a stream (:meth:`FaceVideo.frames`).

Through the camera registry: ``sim://face?basis=builtin&script=training&seed=3&size=360x240&fps=60
&light_drift=0.2&head_turn=10&head_rig=leds&noise=2`` (:func:`open_url`), one
:class:`FaceVideoSource` whose ``truth(seq)`` is the :class:`FaceVideoFrame` of a delivered frame.
"""

from __future__ import annotations

import hashlib
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, replace

import cv2
import numpy as np

from livebridge.calibration.cameras import Camera
from livebridge.capture.frame import Frame
from livebridge.capture.sources import Capabilities, ExposureSetting, SourceBase
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.geometry.transforms import look_at
from livebridge.simulators import raster, skin
from livebridge.simulators.drawing import NoiseTiles, render_discs
from livebridge.simulators.head_rig import LED_DIAMETER_MM, HeadRig, default_head_rig, frame_polyline, load_head_rig
from livebridge.simulators.performer import FACE_SCRIPTS, HeadMotion, contraction_script, head_pivot
from livebridge.simulators.rig import check_range

HEAD_RIGS = ("leds", "none")
SIZE_RANGE = ((32, 4096), (32, 4096))
HEAD_SHIFT_MM_PER_DEG = 1.0  # head translation amplitude per degree of head_turn_deg
LED_MAX_VIEW_DEG = 75.0  # an LED seen further off its axis than this is too dim to show
FOREHEAD = 0.35  # forehead height over the brows-to-chin height
LED_HALO = 1.8  # radius of an LED's halo over its own
FRAME_WIDTH_MM = 2.4  # drawn width of the glasses frame
LIGHT_SWING_DEG = 90.0  # light_drift = 1 swings the light's direction by up to this
DEFAULT_LIGHT = np.array([-0.35, 0.45, 1.0]) / np.linalg.norm([-0.35, 0.45, 1.0])
_RANGES = {  # field: (low, high)
    "fps": (1.0, 1000.0), "seed": (0, 2**32 - 1), "noise": (0.0, 64.0), "exposure": (0.05, 8.0),
    "light_drift": (0.0, 0.9), "head_turn_deg": (0.0, 30.0), "distance_mm": (150.0, 5000.0), "fill": (0.1, 1.5),
    "skin_level": (1.0, 255.0), "ambient": (0.0, 1.0), "specular": (0.0, 2.0), "shininess": (1.0, 500.0),
    "wrinkle": (0.0, 1.0), "background_level": (0.0, 255.0), "led_level": (0.0, 255.0),
}


@dataclass(frozen=True)
class FaceVideoConfig:
    """How the face video is filmed. Defaults: the paper's 360x240 grey camera, still head, steady light.

    Attributes
    ----------
    width, height : int
        Image size, pixels.
    fps : float
    seed : int
        Seeds the skin, the performer's everyday expressions, head motion, light drift and noise.
    skin_seed : int or None
        Seeds the skin instead of ``seed`` (the same performer in takes of other seeds); None: ``seed``.
    noise : float
        Standard deviation of sensor noise, grey levels.
    exposure : float
        Brightness relative to the nominal exposure (1).
    light_drift : float
        The light's intensity drifts by up to this fraction either way (0.2: +-20 %) and its direction by up
        to ``light_drift * LIGHT_SWING_DEG``, smoothly over seconds.
    head_turn_deg : float
        Amplitude of the head's rotation about each axis (and ``HEAD_SHIFT_MM_PER_DEG`` mm of translation
        per degree); 0: the head stays still.
    head_rig : {"leds", "none"}
        "leds": the glasses frame with four LEDs; "none": a bare face (head-mounted camera or chin rest).
    script : str
        Performer script, one of :data:`~livebridge.simulators.performer.FACE_SCRIPTS` ("training":
        isolated sweeps of each muscle; "gestures": those plus the combined gestures; "everyday"; "mixed").
    distance_mm : float
        Camera distance from the face centre.
    fill : float
        Fraction of the image height the face (hairline to chin) fills.
    skin_level : float
        Grey level of white skin fully lit at exposure 1.
    ambient, specular, shininess : float
        Ambient share of the lighting; Blinn-Phong highlight strength and exponent.
    wrinkle : float
        Darkening of fully drawn wrinkles.
    background_level, led_level : float
        Grey levels of the background and of an LED at exposure 1.
    """

    width: int = 360
    height: int = 240
    fps: float = 60.0
    seed: int = 0
    skin_seed: int | None = None
    noise: float = 2.0
    exposure: float = 1.0
    light_drift: float = 0.0
    head_turn_deg: float = 0.0
    head_rig: str = "leds"
    script: str = "training"
    distance_mm: float = 600.0
    fill: float = 0.9
    skin_level: float = 150.0
    ambient: float = 0.3
    specular: float = 0.15
    shininess: float = 20.0
    wrinkle: float = 0.6
    background_level: float = 30.0
    led_level: float = 255.0

    def __post_init__(self):
        for name, (low, high) in zip(("width", "height"), SIZE_RANGE):
            value = getattr(self, name)
            if not isinstance(value, int | np.integer) or isinstance(value, bool) or not low <= value <= high:
                raise InputError(f"{name} must be an integer in {low}..{high}, got {value!r}", field=name)
        for name, (low, high) in _RANGES.items():
            check_range(name, getattr(self, name), low, high, open_low=False, open_high=False)
        if self.head_rig not in HEAD_RIGS:
            raise InputError(f"head_rig must be one of {', '.join(HEAD_RIGS)}, got {self.head_rig!r}",
                             field="head_rig")
        if self.script not in FACE_SCRIPTS:
            raise InputError(f"script must be one of {', '.join(FACE_SCRIPTS)}, got {self.script!r}",
                             field="script")

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)``."""
        return self.width, self.height


@dataclass(frozen=True)
class LightState:
    """The light at one instant.

    Attributes
    ----------
    direction : ndarray, shape (3,)
        Unit vector from the face towards the (distant) light, world frame.
    intensity : float
        Relative to the nominal light (1).
    """

    direction: np.ndarray
    intensity: float = 1.0


@dataclass(frozen=True, eq=False)
class FaceVideoFrame:
    """One rendered frame and its ground truth.

    Attributes
    ----------
    seq : int
    t : float
        Seconds since the start of the take.
    image : ndarray of uint8, shape (height, width)
    contractions : ndarray, shape (n_muscles,)
    head_pose : ndarray, shape (4, 4)
        head -> world, mm.
    led_points_2d : ndarray, shape (4, 2)
        True pixel centre of each LED (the rig's order); NaN where hidden or without a rig.
    light_intensity : float
    light_direction : ndarray, shape (3,)
    gesture : str
        The training gesture being made ("" outside one, and in scripts other than "gestures"/"training").
    """

    seq: int
    t: float
    image: np.ndarray
    contractions: np.ndarray
    head_pose: np.ndarray
    led_points_2d: np.ndarray
    light_intensity: float
    light_direction: np.ndarray
    gesture: str = ""


def shipped_features(basis: Basis) -> dict[str, np.ndarray] | None:
    """Landmark positions on ``basis``'s neutral face when it is one of the shipped faces (the built-in face,
    the ICT-FaceKit face region), else None: ``{name: (3,)}`` (brows, eye corners, mouth, chin ...)."""
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.landmarks import load_landmark_set

    builtin = builtin_basis()
    is_builtin = basis.triangles.shape == builtin.triangles.shape and np.array_equal(basis.triangles,
                                                                                     builtin.triangles)
    landmarks = load_landmark_set("builtin-22" if is_builtin else "ict-22")
    if not is_builtin and landmarks.mesh_triangles != len(basis.triangles):
        return None  # neither shipped face
    return landmarks.as_dict(basis.neutral, basis.triangles)


class FaceVideo:
    """A camera filming a performer's face (see the module docstring).

    Parameters
    ----------
    basis : Basis
        The face: neutral mesh and one displacement field per muscle (mm, +y up, +z out of the face).
    config : FaceVideoConfig
    head_rig : HeadRig, optional
        LED geometry (default: :func:`~livebridge.simulators.head_rig.default_head_rig` fitted to the face).
    features : dict of str to ndarray (3,), optional
        Landmarks on the neutral face that place eyebrows, eyes, lips and the glasses; default: the shipped
        landmarks when ``basis`` is a shipped face (:func:`shipped_features`), else none.
    """

    def __init__(self, basis: Basis, config: FaceVideoConfig | None = None, head_rig: HeadRig | None = None,
                 features: dict[str, np.ndarray] | None = None):
        self.basis = basis
        self.config = config = config or FaceVideoConfig()
        self.features = shipped_features(basis) if features is None else features
        skin_seed = config.seed if config.skin_seed is None else config.skin_seed
        self.skin = _skin_for(basis.neutral, skin_seed, self.features)
        self.head_rig = head_rig or default_head_rig(basis.neutral, self.features)
        self._frame_points = frame_polyline(self.head_rig)
        self._camera, self._target = _frontal_camera(basis.neutral, self.features, config)
        self._world2cam = self._camera.world2cam
        self._matrix = self._camera.matrix
        self._elements = basis.elements.reshape(basis.n_muscles, -1)
        self._triangles = np.ascontiguousarray(basis.triangles, dtype=np.int64)
        self._strain = skin.strain_reference(basis.neutral, self._triangles, self.skin.vertex_texels)
        # the texture level whose texels are about as large as the pixels' footprint on the face (a
        # pre-filtered texture: no aliasing of pores and freckles, and it stays in the cache)
        mm_per_pixel = (config.distance_mm - (basis.neutral[:, 2].max() - self._target[2])) / self._matrix[0, 0]
        self._maps = self.skin.level(mm_per_pixel)
        n_vertices = basis.n_vertices
        self._pixels = np.zeros((n_vertices, 2))
        self._depth = np.zeros(n_vertices)
        self._normals = np.zeros((n_vertices, 3))
        self._compression = np.zeros((n_vertices, 2), dtype=np.float32)
        self._counts = np.zeros(n_vertices)
        self._gbuffer = raster.GBuffer(config.size, len(self._triangles))
        self._shaded = np.zeros((config.height, config.width), dtype=np.float32)
        self._noise = NoiseTiles(config.size, config.noise, config.seed) if config.noise > 0 else None
        self.script = contraction_script(basis.names, config.script, config.seed)
        self._head = (HeadMotion(head_pivot(basis), config.seed, HEAD_SHIFT_MM_PER_DEG * config.head_turn_deg,
                                 config.head_turn_deg) if config.head_turn_deg > 0 else None)
        rng = np.random.default_rng([config.seed, 47])
        self._drift_freq = rng.uniform(0.03, 0.2, size=(3, 3))  # (intensity, azimuth, elevation) x terms
        self._drift_phase = rng.uniform(0, 2 * np.pi, size=(3, 3))
        share = rng.dirichlet(np.ones(3), size=3)
        self._drift_share = share
        self._lock = threading.Lock()  # the buffers are shared: one render at a time

    # ------------------------------------------------------------------------------------ the scene
    def camera(self) -> Camera:
        """The simulator's camera (intrinsics, no distortion, pose in the world frame)."""
        return self._camera

    def head_rig_geometry(self) -> np.ndarray:
        """LED positions in the head frame, mm, shape (4, 3), in the order of ``head_rig.names``."""
        return np.array(self.head_rig.positions)

    def contractions_at(self, t: float) -> np.ndarray:
        """The performer's contractions at ``t`` seconds, shape (n_muscles,)."""
        return self.script(np.array([float(t)]))[0]

    def head_pose_at(self, t: float) -> np.ndarray:
        """head -> world at ``t`` seconds, shape (4, 4) (the identity with ``head_turn_deg = 0``)."""
        return np.eye(4) if self._head is None else self._head(np.array([float(t)]))[0]

    def light_at(self, t: float) -> LightState:
        """The light at ``t`` seconds: the default light, drifted smoothly by ``light_drift``."""
        drift = self.config.light_drift
        if drift == 0:
            return LightState(DEFAULT_LIGHT.copy(), 1.0)
        wave = (self._drift_share * np.sin(2 * np.pi * self._drift_freq * float(t) + self._drift_phase)).sum(axis=1)
        intensity = 1.0 + drift * float(wave[0])
        swing = math.radians(LIGHT_SWING_DEG) * drift
        azimuth = math.atan2(DEFAULT_LIGHT[0], DEFAULT_LIGHT[2]) + swing * float(wave[1])
        elevation = math.asin(DEFAULT_LIGHT[1]) + 0.5 * swing * float(wave[2])
        direction = np.array([math.sin(azimuth) * math.cos(elevation), math.sin(elevation),
                              math.cos(azimuth) * math.cos(elevation)])
        return LightState(direction, intensity)

    def gesture_at(self, t: float) -> str:
        """The training gesture being made at ``t`` ("" in a rest, or when the script has no gestures)."""
        if hasattr(self.script, "gesture_at"):
            index = int(self.script.gesture_at(np.array([float(t)]))[0])
            return self.script.gesture_names[index] if index >= 0 else ""
        if self.config.script == "training":
            from livebridge.simulators.performer import TRAINING_BLOCK_S, TRAINING_REST_S

            local = float(t) % TRAINING_BLOCK_S
            if TRAINING_REST_S < local < TRAINING_BLOCK_S - TRAINING_REST_S:
                return self.basis.names[int(float(t) // TRAINING_BLOCK_S) % self.basis.n_muscles]
        return ""

    # ------------------------------------------------------------------------------------ rendering
    def render(self, contractions: np.ndarray, head_pose: np.ndarray | None = None, light: LightState | None = None,
               seq: int = 0) -> np.ndarray:
        """One image of the face.

        Parameters
        ----------
        contractions : ndarray, shape (n_muscles,)
        head_pose : ndarray, shape (4, 4), optional
            head -> world, mm (default: at rest).
        light : LightState, optional
            Default: the steady default light.
        seq : int
            Picks the sensor noise (the same ``seq`` gives the same noise).

        Returns
        -------
        ndarray of uint8, shape (height, width)
        """
        return self.render_with_leds(contractions, head_pose, light, seq)[0]

    def render_with_leds(self, contractions: np.ndarray, head_pose: np.ndarray | None = None,
                         light: LightState | None = None, seq: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`render` and the true LED pixels, shape (4, 2) (NaN where hidden or without a rig)."""
        contractions = np.asarray(contractions, dtype=np.float64)
        if contractions.shape != (self.basis.n_muscles,):
            raise ValueError(f"contractions must have shape ({self.basis.n_muscles},), got {contractions.shape}")
        head_pose = np.eye(4) if head_pose is None else np.asarray(head_pose, dtype=np.float64)
        light = light or LightState(DEFAULT_LIGHT.copy(), 1.0)
        config = self.config
        model = self.basis.neutral + (contractions @ self._elements).reshape(-1, 3)
        world = model @ head_pose[:3, :3].T + head_pose[:3, 3]
        with self._lock:
            raster.project_vertices(world, self._world2cam, self._matrix, self._pixels, self._depth)
            raster.vertex_normals_into(world, self._triangles, self._normals)
            skin.strain_into(world, self._triangles, *self._strain, self._compression, self._counts)
            self._gbuffer.fill(self._pixels, self._depth, self._triangles)
            centre = head_pose[:3, :3] @ self._target + head_pose[:3, 3]
            to_camera = self._camera.center - centre
            to_camera /= np.linalg.norm(to_camera)
            direction = np.asarray(light.direction, dtype=np.float64)
            direction = direction / np.linalg.norm(direction)
            halfway = direction + to_camera
            halfway /= np.linalg.norm(halfway)
            lighting = np.array([config.skin_level * config.exposure, light.intensity, config.ambient,
                                 config.specular, config.shininess, config.wrinkle])
            maps = self._maps
            gbuffer = self._gbuffer
            skin.shade(gbuffer.ids, gbuffer.bary, gbuffer.front, self._triangles, self._normals,
                       maps.vertex_texels, self._compression, maps.albedo, maps.lines_u, maps.lines_v,
                       direction, halfway, lighting, config.background_level * config.exposure, self._shaded)
            image = np.clip(self._shaded + 0.5, 0.0, 255.0).astype(np.uint8)
            leds = np.full((4, 2), np.nan)
            if config.head_rig == "leds":
                leds = self._draw_rig(image, head_pose)
        if self._noise is not None:
            self._noise.apply(image, np.random.default_rng([config.seed, int(seq), 53]))
        return image, leds

    def _draw_rig(self, image: np.ndarray, head_pose: np.ndarray) -> np.ndarray:
        """Draw the glasses frame (dark) and the LEDs (bright discs) where the face does not hide them; returns
        the LED pixels, shape (4, 2), NaN where hidden."""
        config = self.config
        focal = float(self._matrix[0, 0])
        points, depth = self._project(self._frame_points, head_pose)
        shown = self._unoccluded(points, depth)
        if shown.any():
            render_discs(image, points[shown], focal * FRAME_WIDTH_MM / 2 / depth[shown],
                         np.full(int(shown.sum()), 0.5 * config.background_level * config.exposure))
        leds, led_depth = self._project(self.head_rig.positions, head_pose)
        axis = head_pose[:3, :3] @ np.array([0.0, 0.0, 1.0])  # the LEDs shine out of the face
        world = self.head_rig.positions @ head_pose[:3, :3].T + head_pose[:3, 3]
        to_camera = self._camera.center - world
        cosine = to_camera @ axis / np.linalg.norm(to_camera, axis=1)
        shown = self._unoccluded(leds, led_depth) & (cosine > math.cos(math.radians(LED_MAX_VIEW_DEG)))
        if shown.any():
            radius = focal * LED_DIAMETER_MM / 2 / led_depth[shown]
            level = min(255.0, config.led_level * config.exposure)
            # a halo around the bright core (light scattered in the lens): the blob stands on an even ring
            render_discs(image, leds[shown], LED_HALO * radius, np.full(int(shown.sum()), 0.75 * level))
            render_discs(image, leds[shown], radius, np.full(int(shown.sum()), level))
        return np.where(shown[:, None], leds, np.nan)

    def _project(self, head_points: np.ndarray, head_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (n, 2) and camera depths (n,) of head-frame points."""
        world = head_points @ head_pose[:3, :3].T + head_pose[:3, 3]
        pixels, depth = np.zeros((len(world), 2)), np.zeros(len(world))
        raster.project_vertices(np.ascontiguousarray(world), self._world2cam, self._matrix, pixels, depth)
        return pixels, depth

    def _unoccluded(self, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Points inside the image and in front of the face surface there (the G-buffer), shape (n,) bool."""
        width, height = self.config.size
        inside = np.isfinite(pixels).all(axis=1) & (depth > raster.NEAR_MM)
        inside &= (pixels[:, 0] >= 0) & (pixels[:, 0] <= width - 1) & (pixels[:, 1] >= 0) & (pixels[:, 1] <= height - 1)
        x = np.rint(np.where(inside, pixels[:, 0], 0)).astype(np.int64)
        y = np.rint(np.where(inside, pixels[:, 1], 0)).astype(np.int64)
        inverse = self._gbuffer.inverse_depth[y, x].astype(np.float64)
        surface = np.where(inverse > 0, 1.0 / np.maximum(inverse, 1e-12), np.inf)
        return inside & (depth < surface - 0.5)

    # ------------------------------------------------------------------------------------ the take
    def frame(self, seq: int) -> FaceVideoFrame:
        """Frame ``seq`` of the take (random access; the same as in :meth:`frames`)."""
        t = int(seq) / self.config.fps
        contractions = self.contractions_at(t)
        head_pose = self.head_pose_at(t)
        light = self.light_at(t)
        image, leds = self.render_with_leds(contractions, head_pose, light, seq)
        for array in (image, contractions, head_pose, leds):
            array.setflags(write=False)
        return FaceVideoFrame(int(seq), t, image, contractions, head_pose, leds, float(light.intensity),
                              light.direction, self.gesture_at(t))

    def frames(self, n_frames: int | None = None, start: int = 0) -> Iterator[FaceVideoFrame]:
        """Frames ``start, start + 1, ...``: ``n_frames`` of them, or forever."""
        seq = int(start)
        while n_frames is None or seq < start + n_frames:
            yield self.frame(seq)
            seq += 1


_SKINS: OrderedDict[str, skin.SkinTexture] = OrderedDict()
_SKINS_KEPT = 4


def _skin_for(neutral: np.ndarray, seed: int, features: dict | None) -> skin.SkinTexture:
    """:func:`~livebridge.simulators.skin.make_skin`, remembered for the last few faces (building the texture
    takes about a second; videos of one face and seed share it, read-only)."""
    digest = hashlib.sha1(np.ascontiguousarray(neutral, dtype=np.float64).tobytes())
    digest.update(str(int(seed)).encode())
    for name in sorted(features or {}):
        digest.update(name.encode() + np.asarray(features[name], dtype=np.float64).tobytes())
    key = digest.hexdigest()
    with _SKINS_LOCK:
        if key in _SKINS:
            _SKINS.move_to_end(key)
            return _SKINS[key]
    texture = skin.make_skin(neutral, seed, features)
    for array in (texture.albedo, texture.lines_u, texture.lines_v, texture.vertex_texels):
        array.setflags(write=False)
    with _SKINS_LOCK:
        _SKINS[key] = texture
        while len(_SKINS) > _SKINS_KEPT:
            _SKINS.popitem(last=False)
    return texture


_SKINS_LOCK = threading.Lock()


def _frontal_camera(neutral: np.ndarray, features: dict | None,
                    config: FaceVideoConfig) -> tuple[Camera, np.ndarray]:
    """The camera in front of the face (see the module docstring) and the point it looks at (head frame, (3,))."""
    low, high = neutral.min(axis=0), neutral.max(axis=0)
    if features and all(n in features for n in ("brow_middle_L", "brow_middle_R", "chin")):
        brows = 0.5 * (features["brow_middle_L"][1] + features["brow_middle_R"][1])
        chin = features["chin"][1]
    else:
        brows, chin = low[1] + 0.7 * (high[1] - low[1]), low[1] + 0.15 * (high[1] - low[1])
    top, bottom = brows + FOREHEAD * (brows - chin), chin  # the hairline and the chin
    target = np.array([0.5 * (low[0] + high[0]), 0.5 * (top + bottom), 0.5 * (low[2] + high[2])])
    center = target + np.array([0.0, 0.0, config.distance_mm])
    to_front = config.distance_mm - (high[2] - target[2])
    focal = config.fill * config.height * to_front / max(top - bottom, 1e-6)
    width, height = config.size
    matrix = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]])
    world2cam = look_at(center, target)
    camera = Camera("face", (width, height), matrix, np.zeros(5), cv2.Rodrigues(world2cam[:3, :3])[0].ravel(),
                    world2cam[:3, 3])
    return camera, target


# -------------------------------------------------------------------------------------------- the source

class FaceVideoSource(SourceBase):
    """The face video as a camera source (``sim://face?...``).

    Unpaced (``realtime=False``): every frame in order, as fast as the reader asks. Paced: frame ``seq`` is
    delivered no earlier than the end of its exposure on the host clock, and a reader that falls behind
    skips to the newest frame that is due (``skipped`` counts them). ``truth(seq)`` is the
    :class:`FaceVideoFrame` (ground truth) of a recently delivered frame.
    """

    KEEP = 256  # delivered frames whose truth is kept

    def __init__(self, video: FaceVideo, realtime: bool = True, n_frames: int | None = None):
        self.video, self.realtime, self.n_frames = video, realtime, n_frames
        self.source_id = "face"
        self.skipped = 0
        self.delivered = 0
        self._seq = 0
        self._t0: float | None = None
        self._running = False
        self._truth: OrderedDict[int, FaceVideoFrame] = OrderedDict()
        self._exposure_scale = 1.0

    def start(self) -> None:
        if self._t0 is None:
            self._t0 = time.monotonic()
        self._running = True

    def stop(self) -> None:
        self._running = False
        self._end(None)

    def read(self, timeout: float | None = None) -> Frame | None:
        if not self._running:
            if self._ended:
                return None
            raise RuntimeError(f"{self.source_id}: read() before start()")
        period = 1.0 / self.video.config.fps
        seq = self._seq
        if self.realtime:
            now = time.monotonic()
            due = int(math.floor((now - self._t0) / period - 0.5))
            if due > seq:  # the reader is late: no backlog
                self.skipped += due - seq
                seq = due
            else:
                ready = self._t0 + (seq + 0.5) * period
                if timeout is not None and ready > now + timeout:
                    time.sleep(max(0.0, timeout))
                    return None
                if ready > now:
                    time.sleep(ready - now)
        if self.n_frames is not None and seq >= self.n_frames:
            self._end(None)  # the end of the simulated take
            return None
        self._seq = seq + 1
        truth = self.video.frame(seq)
        self._truth[seq] = truth
        while len(self._truth) > self.KEEP:
            self._truth.popitem(last=False)
        self.delivered += 1
        exposure_us = 0.5e6 / self.video.config.fps * self.video.config.exposure
        return Frame(truth.image, self._t0 + seq * period, seq, self.source_id, exposure_us, 1.0, "simface")

    def truth(self, seq: int) -> FaceVideoFrame:
        """Ground truth (and image) of delivered frame ``seq``; rendered again if no longer kept."""
        return self._truth.get(int(seq)) or self.video.frame(int(seq))

    def set_exposure(self, manual: bool, exposure_us: float | None = None, gain: float | None = None):
        """The simulated camera's exposure is fixed by its URL (``exposure``); reports it."""
        return ExposureSetting(True, 0.5e6 / self.video.config.fps * self.video.config.exposure, 1.0)

    @property
    def calibration(self) -> Camera:
        """The simulated camera: the video is filmed with it."""
        return self.video.camera()

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(size=self.video.config.size, fps=self.video.config.fps, formats=("GREY",))


_URL_KEYS = {"basis", "script", "seed", "skin_seed", "size", "fps", "light_drift", "head_turn", "head_rig", "noise",
             "exposure", "frames", "realtime", "rig_file"}


def video_from_url(url: DeviceURL | str) -> FaceVideo:
    """A :class:`FaceVideo` from ``sim://face?basis=builtin|PATH.npz&script=training&seed=3&size=360x240&fps=60
    &light_drift=0.2&head_turn=10&head_rig=leds|none&noise=2&exposure=1&rig_file=head_rig.toml`` (``frames``
    and ``realtime`` are the source's, see :func:`open_url`). Every value is checked before anything is built;
    an :class:`InputError` names the parameter."""
    if isinstance(url, str):
        url = DeviceURL.parse(url)
    if url.netloc != "face":
        raise InputError(f"unknown simulator {url.netloc!r}; known: rig, face", url.url)
    url.check_known(_URL_KEYS)
    changes = {}
    for key, name, kind in (("seed", "seed", int), ("skin_seed", "skin_seed", int), ("fps", "fps", float),
                            ("light_drift", "light_drift", float),
                            ("head_turn", "head_turn_deg", float), ("noise", "noise", float),
                            ("exposure", "exposure", float), ("head_rig", "head_rig", str),
                            ("script", "script", str)):
        value = url.take(key, kind)
        if value is not None:
            changes[name] = value
    if "size" in url.query:
        try:
            width, height = (int(v) for v in url.query["size"].lower().split("x"))
        except ValueError:
            raise InputError(f"size must look like 360x240, got {url.query['size']!r}", url.url, "size") from None
        changes["width"], changes["height"] = width, height
    frames = url.take("frames", int)
    if frames is not None and not 1 <= frames <= 10**9:
        raise InputError(f"frames must be an integer in 1..{10**9}, got {frames}", url.url, "frames")
    try:
        config = replace(FaceVideoConfig(), **changes)
    except InputError as error:  # named by the URL's parameter, not the config field
        field = {"head_turn_deg": "head_turn", "width": "size", "height": "size"}.get(error.field, error.field)
        raise InputError(error.message, url.url, field) from None
    basis = _basis_from(url)
    head_rig = load_head_rig(url.query["rig_file"]) if "rig_file" in url.query else None
    return FaceVideo(basis, config, head_rig=head_rig)


def _basis_from(url: DeviceURL) -> Basis:
    """``basis=builtin`` (default) or ``basis=PATH.npz`` (a saved basis, e.g. from ``livebridge basis import``)."""
    spec = url.query.get("basis", "builtin")
    if spec == "builtin":
        from livebridge.face.builtin import builtin_basis

        return builtin_basis()
    if not spec.endswith(".npz"):
        raise InputError(f"basis must be 'builtin' or a basis file PATH.npz, got {spec!r}", url.url, "basis")
    return Basis.load(spec)


def open_url(url: DeviceURL) -> list[FaceVideoSource]:
    """The registry hook (dispatched from ``sim://``): one source; ``frames=N`` ends the take after frame
    ``N - 1``; ``realtime=0`` delivers frames as fast as they are read."""
    realtime = url.take("realtime", bool, True)
    video = video_from_url(url)
    return [FaceVideoSource(video, realtime, url.take("frames", int))]

"""The session file: everything one live run needs, in one TOML file, checked before anything starts.

Example (every table but ``[cameras]`` is optional, and a phone session has none; paths are relative to
the session file; top-level keys such as ``calibration`` must come before the first ``[table]``, or TOML
puts them in that table)::

    calibration = "calibration.toml"  # written by `livebridge calibrate` (save_calibration); sim:// rigs
                                      # film with these cameras; not needed by a sim rig of its own, by
                                      # replay:// of a recorded take (its calibration.toml is used) or by
                                      # node:// cameras whose node knows their calibration

    [source]                      # optional; what the pipeline reads
    kind = "cameras"              # default: the [cameras] below; or "livelinkface": an iPhone running Live
                                  # Link Face (then no [cameras] or calibration), with:
    # url = "livelinkface://127.0.0.1:11111"   # where to listen (this default); the network is heard only
    #                             # on a named address: "livelinkface://0.0.0.0:11111"; "?device=ID" follows
    #                             # one phone (default: the first heard); or a recorded phone take, solved
    #                             # again: "replay://takes/take-20250101-120000?realtime=1&loop=0"
    # arkit_shapes = "face_region.npz"  # optional: ARKit-named shapes on the basis's mesh (.npz of names (n,)
    #                             # and deltas (n, V, 3), ICT-FaceKit's layout; ARKit names or NAME_L/NAME_R);
    #                             # default: synthesised from the basis's muscles
    # arkit_shapes_units = "cm"   # of arkit_shapes: "mm", "cm" (ICT-FaceKit's face_region.npz), "m"

    [cameras]
    urls = ["v4l2:///dev/video0?fps=60", "v4l2:///dev/video2?fps=60"]
    # or ["sim://rig?cameras=4&seed=1"], or ["replay://takes/take-20250101-120000?realtime=0"], or camera
    # nodes on other PCs: ["node://10.0.0.5:7000?camera=cam0", "node://10.0.0.6:7000?camera=cam1", ...]
    sync_tolerance = 0.5          # frame periods, for cameras in different sync domains

    [face]
    basis = "basis.npz"           # or "builtin" (the built-in face)
    markers = "markers.toml"      # or a shipped set: "builtin", "builtin-68", "ict-68"
    # display = "target.npz"      # the render client shows this face instead of the basis (same muscles, any
                                  # topology: from `livebridge retarget basis`)
    # display_mode = "instead"    # or "beside": the solving face and the display face side by side

    [reconstruct]
    tolerance_px = 2.0            # epipolar gate
    max_residual_px = 2.0         # outlier view rejection (one tolerance does both: the smaller is used)

    [solver]
    mode = "split-compensated"    # "split", "joint"
    exaggerate = false
    sweeps = 2

    [servo]
    rig = "head.toml"             # the servo rig file (buses by URL, servos, limits)

    [outputs.render]
    enabled = true
    host = "127.0.0.1"
    port = 8765                   # 0: any free port
    allowed_origins = []          # other pages that may connect, e.g. ["https://studio.example:8443"]

    [outputs.vmc]
    enabled = false
    host = "127.0.0.1"
    port = 39539
    case = "camel"                # "pascal", "lower", "snake"
    mapping = { jaw = { jawOpen = 1.0 } }   # optional; default ARKit names

    [outputs.livelink]            # Live Link Face packets to Unreal Engine
    enabled = false
    host = "127.0.0.1"
    port = 11111
    subject = "livebridge"        # the Live Link subject name
    device_id = "..."             # default: a UUID stable on this machine
    fps = 60                      # the frame rate of the packets' frame time
    # the muscle -> blendshape map is [outputs.vmc]'s (one map, two transports)

    [recording]
    enabled = false
    directory = "takes"           # each run writes a new take directory inside
    raw_frames = false            # also the camera images: replay://takes/take-... runs the take again
                                  # (a phone session records the phone's packets instead: always)
    frame_format = "pgm"          # raw images: "pgm" (uncompressed, keeps up live) or "png" (smaller, slow)

    # [markerless]                # instead of markers: ONE camera URL filming a bare face (no calibration)
    # model = "model.npz"         # from `livebridge markerless train`
    # head_rig = "leds"           # "leds" or "none" (optional: checked against the model)
    # min_confidence = 0.3        # a region less sure than this holds its last state

    [runtime]
    status_interval = 1.0         # seconds between live status lines
    frames = 0                    # stop after this many frame sets (0: until Ctrl-C)
    labelling_timeout_s = 10.0    # no first labelling by then: end, saying what the cameras saw (0: wait)

Unknown keys are errors (a misspelt key would otherwise be silently ignored); every error names the
file and the dotted field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from livebridge.errors import InputError
from livebridge.tomlio import load_toml

if TYPE_CHECKING:
    from livebridge.reconstruct.pipeline import ReconstructConfig
    from livebridge.servo.rig import Rig
    from livebridge.solve.solver import SolverConfig

BUILTIN_NAMES = ("builtin",)
SELF_CALIBRATED = ("sim://", "replay://", "node://")  # cameras that may know their own calibration
LABELLING_TIMEOUT_S = 10.0  # default [runtime] labelling_timeout_s
_TOP_KEYS = {"source", "cameras", "face", "calibration", "reconstruct", "solver", "servo", "outputs", "recording",
             "runtime", "markerless"}


SOURCE_KINDS = ("cameras", "livelinkface")


@dataclass(frozen=True)
class SourceOptions:
    """``[source]``: ``kind`` "cameras" (the session's ``camera_urls``) or "livelinkface" (``url``, the receiver's
    ``livelinkface://`` URL, or a phone take's ``replay://`` URL, its folder resolved; ``arkit_shapes``, an ARKit
    shape set on the basis's mesh, None: synthesised from the basis's muscles, in ``arkit_shapes_units``)."""

    kind: str = "cameras"
    url: str = "livelinkface://127.0.0.1:11111"
    arkit_shapes: Path | None = None
    arkit_shapes_units: str = "cm"


@dataclass(frozen=True)
class RenderOptions:
    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 8765
    allowed_origins: tuple[str, ...] = ()


@dataclass(frozen=True)
class MarkerlessOptions:
    """``[markerless]``: the camera films a bare face analysed with a trained model (``livebridge markerless
    train``) instead of markers; ``head_rig`` ("leds" or "none"), when given, must be the model's."""

    model: Path
    head_rig: str | None = None
    min_confidence: float = 0.3


@dataclass(frozen=True)
class VMCOptions:
    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 39539
    case: str = "camel"
    mapping: Any = None  # None (ARKit), "identity", or {muscle: {blendshape: weight}}


@dataclass(frozen=True)
class LiveLinkOptions:
    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 11111
    subject: str = "livebridge"
    device_id: str | None = None  # None: stable per machine
    fps: int = 60


@dataclass(frozen=True)
class RecordingOptions:
    """``[recording]``; ``take_name`` (not in the file): the take directory's name inside ``directory``
    (default ``take-YYYYmmdd-HHMMSS`` of the start)."""

    enabled: bool = False
    directory: Path | None = None
    raw_frames: bool = False
    frame_format: str = ".pgm"
    take_name: str | None = None


def _reconstruct_config() -> ReconstructConfig:
    from livebridge.reconstruct.pipeline import ReconstructConfig

    return ReconstructConfig()


def _solver_config() -> SolverConfig:
    from livebridge.solve.solver import SolverConfig

    return SolverConfig()


@dataclass(frozen=True)
class Session:
    """A validated session file.

    Attributes
    ----------
    path : Path or None
        The session file (None for a session built in code).
    camera_urls : tuple of str
        Empty for a session whose source is not cameras.
    sync_tolerance : float
        Frame periods.
    basis : Path or str
        A ``.npz`` path, or ``"builtin"``.
    markers : Path or str or None
        A marker-set TOML path, a shipped set's name (``"builtin"``, ``"builtin-68"``, ``"ict-68"``), or None
        (the rig's / built-in markers).
    calibration : Path or None
    reconstruct : ReconstructConfig
        The reconstruction stage's configuration (the file's ``tolerance_px`` and ``max_residual_px``: the
        smaller of the two, since the reconstructor uses one tolerance for gating and residuals).
    solver : SolverConfig
    servo_rig : Path or Rig or None
        A servo rig file (read with the face's muscle names when the pipeline is built), or a rig made in
        code (the demo's).
    render, vmc, recording, livelink : option records
    source : SourceOptions
    status_interval : float
    frames : int
        0: run until stopped.
    labelling_timeout_s : float
        Seconds the pipeline waits for its first labelling before it ends with the reason; 0: forever.
    display : Path or None
        A basis ``.npz`` the render client shows instead of ``basis`` (same muscles, any topology: a
        retargeted face), or None.
    display_mode : str
        ``"instead"`` (the display face alone) or ``"beside"`` (the solving face and the display face side by
        side).
    source : SourceOptions
        What drives the face: cameras (``camera_urls``) or a phone (Live Link Face).
    markerless : MarkerlessOptions or None
        Markerless capture (one camera, a trained model) instead of markers.
    """

    path: Path | None
    camera_urls: tuple[str, ...]
    sync_tolerance: float = 0.5
    basis: Path | str = "builtin"
    markers: Path | str | None = None
    calibration: Path | None = None
    reconstruct: ReconstructConfig = field(default_factory=_reconstruct_config)
    solver: SolverConfig = field(default_factory=_solver_config)
    servo_rig: Path | Rig | None = None
    render: RenderOptions = RenderOptions()
    vmc: VMCOptions = VMCOptions()
    recording: RecordingOptions = RecordingOptions()
    livelink: LiveLinkOptions = LiveLinkOptions()
    status_interval: float = 1.0
    frames: int = 0
    labelling_timeout_s: float = LABELLING_TIMEOUT_S
    display: Path | None = None
    display_mode: str = "instead"
    source: SourceOptions = SourceOptions()
    markerless: MarkerlessOptions | None = None


DISPLAY_MODES = ("instead", "beside")


class _Table:
    """Typed, named access to one TOML table; remembers the keys read to reject unknown ones."""

    def __init__(self, data: Any, path: Path | None, prefix: str):
        if not isinstance(data, dict):
            raise InputError(f"expected a table, got {type(data).__name__}", path, prefix or None)
        self.data, self.path, self.prefix, self.read = data, path, prefix, set()

    def _field(self, key: str) -> str:
        return f"{self.prefix}.{key}" if self.prefix else key

    def get(self, key: str, kind, default=None, required: bool = False):
        self.read.add(key)
        if key not in self.data:
            if required:
                raise InputError("missing", self.path, self._field(key))
            return default
        value = self.data[key]
        kinds = kind if isinstance(kind, tuple) else (kind,)
        if isinstance(value, bool) and bool not in kinds or not isinstance(value, kinds):
            if float in kinds and isinstance(value, int) and not isinstance(value, bool):
                return float(value)
            names = " or ".join(k.__name__ for k in kinds)
            raise InputError(f"expected {names}, got {type(value).__name__} {value!r}", self.path, self._field(key))
        return value

    def table(self, key: str) -> _Table:
        self.read.add(key)
        return _Table(self.data.get(key, {}), self.path, self._field(key))

    def path_value(self, key: str, builtins: tuple[str, ...] = (), must_exist: bool = True,
                   required: bool = False, default=None):
        value = self.get(key, str, None, required)
        if value is None:
            return default
        if value in builtins:
            return value
        base = self.path.parent if self.path is not None else Path.cwd()
        resolved = (base / value).resolve() if not Path(value).is_absolute() else Path(value)
        if must_exist and not resolved.exists():
            raise InputError(f"file not found: {resolved}", self.path, self._field(key))
        return resolved

    def check_known(self, known: set[str] | None = None) -> None:
        unknown = sorted(set(self.data) - (known if known is not None else self.read))
        if unknown:
            raise InputError(f"unknown key {unknown[0]!r}", self.path, self._field(unknown[0]))


def _positive(value, path, name, allow_zero=False):
    if value is not None and not ((value > 0 or allow_zero and value == 0) and math.isfinite(value)):
        raise InputError(f"must be a finite number {'>= 0' if allow_zero else '> 0'}, got {value}", path, name)
    return value


def _port(value, path, name, any_free: bool = False):
    """A port number; 0 (the system picks a free one) only where ``any_free``: a server's, not a destination's."""
    low = 0 if any_free else 1
    if not low <= value <= 65535:
        raise InputError(f"port must be in {low}..65535, got {value}", path, name)
    return value


def _origins(values: list, path) -> tuple[str, ...]:
    from livebridge.output.render_server import parse_origin

    for k, value in enumerate(values):
        try:
            parse_origin(value)
        except InputError as error:
            raise InputError(error.message, path, f"outputs.render.allowed_origins[{k}]") from None
    return tuple(values)


def session_from_dict(data: dict, path: Path | None = None) -> Session:
    """Validate a parsed session table (``path`` names the file in errors and anchors relative paths)."""
    path = Path(path) if path is not None else None
    top = _Table(data, path, "")
    top.check_known(_TOP_KEYS)

    source = _source(top.table("source"), path)
    urls, sync_tolerance = [], 0.5
    if source.kind == "cameras":
        cameras = top.table("cameras")
        urls = cameras.get("urls", list, required=True)
        if not urls or not all(isinstance(u, str) and "://" in u for u in urls):
            raise InputError("a non-empty list of camera URLs (scheme://...)", path, "cameras.urls")
        sync_tolerance = _positive(cameras.get("sync_tolerance", float, 0.5), path, "cameras.sync_tolerance")
        if sync_tolerance > 0.5:
            raise InputError("at most half a frame period", path, "cameras.sync_tolerance")
        cameras.check_known()
    else:
        for key in ("cameras", "calibration"):
            if key in data:
                raise InputError(f"a {source.kind} session has no {key} (the phone sends ARKit weights, "
                                 "not images)", path, key)

    face = top.table("face")
    basis = face.path_value("basis", BUILTIN_NAMES, default="builtin")
    if isinstance(basis, Path) and basis.suffix != ".npz":
        raise InputError("a basis .npz file (from `livebridge basis import`) or 'builtin'", path, "face.basis")
    from livebridge.face import SHIPPED_MARKER_SETS

    markers = face.path_value("markers", SHIPPED_MARKER_SETS)
    display = face.path_value("display")
    if display is not None and Path(display).suffix != ".npz":
        raise InputError("a basis .npz file to show (e.g. from `livebridge retarget basis`)", path, "face.display")
    display_mode = face.get("display_mode", str, "instead")
    if display_mode not in DISPLAY_MODES:
        raise InputError(f"must be one of {', '.join(DISPLAY_MODES)}, got {display_mode!r}", path,
                         "face.display_mode")
    face.check_known()

    markerless = _markerless(top.table("markerless"), path) if "markerless" in data else None
    calibration = top.path_value("calibration")
    if markerless is not None and source.kind != "cameras":
        raise InputError(f"markerless capture films with a camera, not a {source.kind} source", path, "markerless")
    if markerless is not None and len(urls) != 1:
        raise InputError(f"markerless capture films with one camera, got {len(urls)} URLs", path, "cameras.urls")
    if (source.kind == "cameras" and calibration is None and markerless is None
            and not all(u.startswith(SELF_CALIBRATED) for u in urls)):
        raise InputError("real cameras need a calibration file", path, "calibration")

    reconstruct_config = _reconstruct(top.table("reconstruct"), path)
    solver_config = _solver(top.table("solver"), path)

    servo = top.table("servo")
    servo_rig = servo.path_value("rig")
    servo.check_known()

    outputs = top.table("outputs")
    outputs.check_known({"render", "vmc", "livelink"})
    r = outputs.table("render")
    render = RenderOptions(r.get("enabled", bool, True), r.get("host", str, "127.0.0.1"),
                           _port(r.get("port", int, 8765), path, "outputs.render.port", any_free=True),
                           _origins(r.get("allowed_origins", list, []), path))
    r.check_known()
    v = outputs.table("vmc")
    mapping = v.get("mapping", (dict, str))
    if isinstance(mapping, str) and mapping != "identity":
        raise InputError("a table {muscle = {blendshape = weight}} or 'identity'", path, "outputs.vmc.mapping")
    vmc = VMCOptions(v.get("enabled", bool, False), v.get("host", str, "127.0.0.1"),
                     _port(v.get("port", int, 39539), path, "outputs.vmc.port"), v.get("case", str, "camel"), mapping)
    v.check_known()
    from livebridge.output.blendshapes import CASES

    if vmc.case not in CASES:
        raise InputError(f"must be one of {CASES}, got {vmc.case!r}", path, "outputs.vmc.case")

    livelink = _livelink(outputs.table("livelink"), path)

    rec = top.table("recording")
    recording = RecordingOptions(rec.get("enabled", bool, False),
                                 rec.path_value("directory", must_exist=False, default=None),
                                 rec.get("raw_frames", bool, False), "." + rec.get("frame_format", str, "pgm"))
    if recording.enabled and recording.directory is None:
        raise InputError("recording is enabled: give the directory for takes", path, "recording.directory")
    if recording.raw_frames and source.kind != "cameras":
        raise InputError("raw frames are camera images; a phone sends none (its take records the phone's "
                         "packets)", path, "recording.raw_frames")
    from livebridge.take.directory import FRAME_FORMATS

    if recording.frame_format not in FRAME_FORMATS:
        raise InputError(f"must be {' or '.join(repr(f[1:]) for f in FRAME_FORMATS)}, "
                         f"got {recording.frame_format[1:]!r}", path, "recording.frame_format")
    rec.check_known()

    runtime = top.table("runtime")
    status_interval = _positive(runtime.get("status_interval", float, 1.0), path, "runtime.status_interval")
    frames = _positive(runtime.get("frames", int, 0), path, "runtime.frames", allow_zero=True)
    labelling_timeout_s = _positive(runtime.get("labelling_timeout_s", float, LABELLING_TIMEOUT_S), path,
                                    "runtime.labelling_timeout_s", allow_zero=True)
    runtime.check_known()

    return Session(path, tuple(urls), sync_tolerance, basis, markers, calibration, reconstruct_config,
                   solver_config, servo_rig, render, vmc, recording, livelink=livelink,
                   status_interval=status_interval, frames=frames, labelling_timeout_s=labelling_timeout_s,
                   display=display, display_mode=display_mode, source=source, markerless=markerless)


def _phone_url(url: str, path: Path | None) -> str:
    """A phone source's URL, checked: a receiver's, or a take's ``replay://`` (a relative take folder made
    relative to the session file's)."""
    from livebridge.arkit.receiver import parse_receiver_url
    from livebridge.take.phone_replay import SCHEME, parse_replay_url

    if not url.lower().startswith(f"{SCHEME}:"):
        parse_receiver_url(url)
        return url
    take, _, _ = parse_replay_url(url)
    if take.is_absolute() or path is None:
        return url
    query = url.partition("?")[2]
    return f"{SCHEME}://{(path.parent / take).resolve()}" + (f"?{query}" if query else "")


def _source(table: _Table, path: Path | None) -> SourceOptions:
    """``[source]``: the kind, and for a phone its receiver URL (checked now) and ARKit shape set."""
    from livebridge.arkit.shapes import UNITS_TO_MM

    kind = table.get("kind", str, "cameras")
    if kind not in SOURCE_KINDS:
        raise InputError(f"must be one of {', '.join(map(repr, SOURCE_KINDS))}, got {kind!r}", path, "source.kind")
    if kind == "cameras":
        table.check_known({"kind"})
        return SourceOptions()
    url = table.get("url", str, SourceOptions.url)
    try:
        url = _phone_url(url, path)
    except InputError as error:
        inner = f"{error.field}: {error.message}" if error.field else error.message
        raise InputError(f"{url}: {inner}", path, "source.url") from None
    shapes = table.path_value("arkit_shapes")
    if shapes is not None and shapes.suffix != ".npz":
        raise InputError("an .npz of ARKit-named shapes (names, deltas)", path, "source.arkit_shapes")
    units = table.get("arkit_shapes_units", str, "cm")
    if units not in UNITS_TO_MM:
        raise InputError(f"must be one of {', '.join(map(repr, UNITS_TO_MM))}, got {units!r}", path,
                         "source.arkit_shapes_units")
    table.check_known()
    return SourceOptions(kind, url, shapes, units)


def _livelink(table: _Table, path: Path | None) -> LiveLinkOptions:
    """``[outputs.livelink]``: names of at most 256 bytes (what Unreal reads), a whole frame rate."""
    options = LiveLinkOptions(table.get("enabled", bool, False), table.get("host", str, "127.0.0.1"),
                              _port(table.get("port", int, 11111), path, "outputs.livelink.port"),
                              table.get("subject", str, "livebridge"), table.get("device_id", str),
                              table.get("fps", int, 60))
    table.check_known()
    for key in ("subject", "device_id"):
        value = getattr(options, key)
        if value is not None and not 1 <= len(value.encode("utf-8")) <= 256:
            raise InputError("must be 1..256 bytes of text", path, f"outputs.livelink.{key}")
    if not 1 <= options.fps <= 1000:
        raise InputError(f"must be 1..1000 frames per second, got {options.fps}", path, "outputs.livelink.fps")
    return options


def _markerless(table: _Table, path: Path | None) -> MarkerlessOptions:
    model = table.path_value("model", required=True)
    head_rig = table.get("head_rig", str)
    if head_rig is not None and head_rig not in ("leds", "none"):
        raise InputError(f"must be 'leds' or 'none', got {head_rig!r}", path, "markerless.head_rig")
    min_confidence = table.get("min_confidence", float, 0.3)
    if not 0.0 <= min_confidence <= 1.0:
        raise InputError(f"must be in [0, 1], got {min_confidence}", path, "markerless.min_confidence")
    table.check_known()
    return MarkerlessOptions(model, head_rig, min_confidence)


def _reconstruct(table: _Table, path: Path | None) -> ReconstructConfig:
    """``[reconstruct]``: ``tolerance_px`` and ``max_residual_px`` set the one tolerance (the smaller)."""
    tolerances = [_positive(table.get(key, float), path, f"reconstruct.{key}")
                  for key in ("tolerance_px", "max_residual_px")]
    table.check_known()
    config = _reconstruct_config()
    given = [value for value in tolerances if value is not None]
    return replace(config, tolerance_px=min(given)) if given else config


def _solver(table: _Table, path: Path | None) -> SolverConfig:
    """``[solver]``: :class:`~livebridge.solve.solver.SolverConfig`, its errors named ``solver.FIELD``."""
    from livebridge.solve.solver import SolverConfig

    options = {}
    for key, kind in (("mode", str), ("exaggerate", bool), ("sweeps", int)):
        value = table.get(key, kind)
        if value is not None:
            options[key] = value
    table.check_known()
    try:
        return SolverConfig(**options)
    except InputError as error:
        raise InputError(error.message, path, f"solver.{error.field}") from None


def load_session(path: str | Path) -> Session:
    """Read and validate a session file; errors name the file and the field."""
    path = Path(path).resolve()
    return session_from_dict(load_toml(path), path)

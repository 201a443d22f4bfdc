"""From a validated :class:`~livebridge.runtime.session.Session` to a ready (not started) pipeline.

Everything that can fail on bad input is opened here, before any camera streams or servo moves:
the basis, the marker set, the calibration, every camera URL, the servo rig (buses opened and
servos checked), the render port, the VMC host and the take directory. On an error, whatever was
already opened is closed again.
"""

from __future__ import annotations

import datetime
from pathlib import Path

from livebridge.errors import InputError
from livebridge.runtime.session import Session


def load_face(session: Session, rig=None):
    """The session's basis and marker set (a simulated rig's own face when the session names none)."""
    from livebridge.face.basis import Basis
    from livebridge.face.markers import MarkerSet

    explicit_basis = session.path is not None and session.basis != "builtin"
    if rig is not None and not explicit_basis and session.markers is None:
        return rig.basis, rig.markers
    if session.basis == "builtin":
        from livebridge.face.builtin import builtin_basis

        basis = builtin_basis()
    elif session.basis == "ict":
        from livebridge.face.reference import ict_basis

        basis = ict_basis()
        if basis is None:
            raise InputError("the ICT reference data is not on this machine", session.path, "face.basis")
    else:
        basis = Basis.load(session.basis)
    if session.markers is None:
        if session.basis != "builtin":
            raise InputError("a marker set is needed for this basis", session.path, "face.markers")
        from livebridge.face.builtin import builtin_markers

        markers = builtin_markers()
    elif session.markers == "builtin":
        from livebridge.face.builtin import builtin_markers

        markers = builtin_markers()
    else:
        markers = MarkerSet.load(session.markers)
    try:
        markers.check_mesh(len(basis.triangles))
    except InputError as error:
        raise InputError(error.message, session.path, "face.markers") from None
    return basis, markers


def _load_calibration(path: Path):
    from livebridge.calibration.calibfile import load_calibration

    return load_calibration(path)


def _session_url(url: str, session: Session) -> str:
    """A camera URL as the session means it: a relative ``replay://`` path is relative to the session file,
    and a simulated rig films with the session's calibrated cameras unless its URL names a calibration."""
    from urllib.parse import quote, urlsplit

    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme == "replay" and session.path is not None:
        path = parts.netloc + parts.path if parts.netloc else parts.path
        if path and not Path(path).is_absolute():
            resolved = (session.path.parent / path).resolve()
            return f"replay://{resolved}" + (f"?{parts.query}" if parts.query else "")
    if scheme == "sim" and session.calibration is not None and "calibration=" not in parts.query:
        joiner = "&" if parts.query else "?"
        return url + f"{joiner}calibration={quote(str(session.calibration), safe='/')}"
    return url


def _recorded_calibration(sources) -> Path | None:
    """The calibration a recorded take was made with, when every source replays the same take directory."""
    from livebridge.capture.replay import ReplaySource

    folders = {getattr(s, "folder", None) for s in sources}
    if not sources or not all(isinstance(s, ReplaySource) for s in sources) or len(folders) != 1:
        return None
    folder = next(iter(folders))
    for take in (folder, folder.parent):
        if (take / "take.toml").is_file() and (take / "calibration.toml").is_file():
            return take / "calibration.toml"
    return None


def open_cameras(session: Session, log=None):
    """Open every camera URL; returns ``(sources, cameras (CameraGroup), sim rig or None, realtime)``.

    Cameras are matched to the session's calibration by name. Without a calibration file, a simulated rig
    uses its own cameras, and replays of one recorded take directory use the calibration recorded with it.
    """
    from livebridge.calibration.cameras import CameraGroup
    from livebridge.capture.sources import open_sources

    calibrated = _load_calibration(session.calibration) if session.calibration is not None else None
    sources = []
    for k, url in enumerate(session.camera_urls):
        try:
            sources += open_sources(_session_url(url, session))
        except InputError as error:
            inner = error.message if error.path in (None, url) and error.field is None else str(error)
            raise InputError(f"{url}: {inner}", session.path, f"cameras.urls[{k}]") from None
    rigs = {id(s.rig): s.rig for s in sources if hasattr(s, "rig")}
    rig = next(iter(rigs.values())) if len(rigs) == 1 and all(hasattr(s, "rig") for s in sources) else None
    calibration, field = session.calibration, "calibration"
    if calibration is None and rig is None:
        calibration = _recorded_calibration(sources)
        field = "cameras.urls"
        if calibration is not None and log is not None:
            log(f"using the calibration recorded with the take: {calibration}")
    if calibration is not None:
        cameras = calibrated if calibrated is not None else _load_calibration(calibration)
        by_name = {c.name: c for c in cameras.cameras}
        missing = [s.source_id for s in sources if s.source_id not in by_name]
        if missing:
            raise InputError(f"no calibration for camera {missing[0]!r} in {calibration}; calibrated: "
                             f"{', '.join(by_name)}", session.path, field)
        cameras = CameraGroup([by_name[s.source_id] for s in sources])
    elif rig is not None:
        cameras = rig.cameras
    else:
        raise InputError("these cameras need a calibration file", session.path, "calibration")
    realtime = all(getattr(s, "realtime", True) for s in sources)
    return sources, cameras, rig, realtime


def build_pipeline(session: Session, log=print, on_frame=None):
    """The pipeline a session describes, with every output opened (see the module docstring)."""
    from livebridge.reconstruct.pipeline import ReconstructConfig
    from livebridge.runtime.pipeline import Pipeline
    from livebridge.solve.solver import SolverConfig

    sources, cameras, rig, realtime = open_cameras(session, log)
    basis, markers = load_face(session, rig)
    options = dict(session.reconstruct)
    if "max_residual_px" in options:  # the reconstructor uses one tolerance for gating and residuals
        options["tolerance_px"] = min(options.get("tolerance_px", options["max_residual_px"]),
                                      options.pop("max_residual_px"))
    reconstruct_config = ReconstructConfig(**options)
    solver_config = SolverConfig(**session.solver)
    period = 1.0 / (rig.config.fps if rig is not None else _fps(sources))
    opened = []
    try:
        servo = None
        if session.servo_rig is not None:
            from livebridge.servo.output import ServoOutput
            from livebridge.servo.rig import load_rig

            servo = ServoOutput(load_rig(session.servo_rig, basis.names), basis.names, log=log, poll_every=15)
            servo.configure()
            opened.append(lambda: servo.close(ease=False))
        render = None
        if session.render.enabled:
            from livebridge.output.render_server import RenderServer

            render = RenderServer(basis, markers, session.render.host, session.render.port,
                                  servo_names=servo.servo_names if servo is not None else (),
                                  allowed_origins=session.render.allowed_origins)
        vmc = None
        if session.vmc.enabled:
            from livebridge.output.vmc import VMCOutput

            try:
                vmc = VMCOutput(basis.names, session.vmc.host, session.vmc.port, session.vmc.mapping,
                                session.vmc.case)
            except InputError as error:
                raise InputError(error.message, session.path, f"outputs.vmc.{error.field}") from None
            opened.append(vmc.close)
        recorder = None
        if session.recording.enabled:
            from livebridge.output.record import TakeRecorder

            stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
            directory = session.recording.directory / f"take-{stamp}"
            recorder = TakeRecorder(directory, basis.names, markers.names, session.path, session.calibration,
                                    fps=1.0 / period, record_frames=session.recording.raw_frames, cameras=cameras,
                                    lossless_frames=not realtime, frame_format=session.recording.frame_format)
            opened.append(recorder.close)
            sources = recorder.wrap_sources(sources)
            log(f"recording to {directory}" + (" (with raw frames)" if session.recording.raw_frames else ""))
        return Pipeline(sources, cameras, basis, markers, period, reconstruct_config, solver_config, servo=servo,
                        render=render, vmc=vmc, recorder=recorder, sync_tolerance=session.sync_tolerance,
                        realtime=realtime, log=log, on_frame=on_frame, status_interval=session.status_interval)
    except BaseException:
        for close in reversed(opened):
            close()
        raise


def _fps(sources) -> float:
    import math

    rates = [s.capabilities.fps for s in sources]
    rates = [r for r in rates if r and math.isfinite(r)]
    if not rates:
        raise InputError("the cameras do not report a frame rate; set fps in their URLs")
    return min(rates)

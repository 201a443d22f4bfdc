"""From a validated :class:`~livebridge.runtime.session.Session` to a ready (not started) pipeline.

Everything that can fail on bad input is opened here, before any camera streams or servo moves:
the basis, the marker set, the calibration, every camera URL (or the phone's receiver), the servo rig (buses opened and
servos checked), the render port, the VMC host and the take directory. A rig that could never solve
(one camera, cameras at one place, too few markers, calibrated cameras left out) is refused here too
(:mod:`livebridge.runtime.preflight`). On an error, whatever was already opened is closed again.
"""

from __future__ import annotations

import datetime
import functools
from pathlib import Path

from livebridge.devices.registry import open_cameras, stop_sources
from livebridge.errors import InputError
from livebridge.runtime.preflight import check_calibration_used, check_cameras, check_markers
from livebridge.runtime.session import Session


def display_face(session, basis):
    """The basis the render client shows: ``[face] display`` (same muscles in the same order) instead of
    ``basis``, or both side by side (``display_mode = "beside"``: the solving face stays in place, the display
    face to its right), else ``basis``."""
    if session.display is None:
        return basis
    from livebridge.face.basis import Basis

    shown = Basis.load(session.display)
    if shown.names != basis.names:
        raise InputError(f"the display face's muscles ({', '.join(shown.names)}) are not the solving basis's "
                         f"({', '.join(basis.names)}): retarget the solving basis onto it", session.display,
                         "face.display")
    if session.display_mode == "beside":
        from livebridge.retarget.compare import side_by_side

        return side_by_side(basis, shown)
    return shown


def load_face(session: Session):
    """The session's basis and marker set (``builtin`` / ``ict`` or files; a simulated rig films this face)."""
    from livebridge.face.basis import Basis
    from livebridge.face.shipped import load_marker_set

    if session.basis == "builtin":
        from livebridge.face.builtin import builtin_basis

        basis = builtin_basis()
    else:
        basis = Basis.load(session.basis)
    if session.markers is None:
        if session.basis != "builtin":
            raise InputError("a marker set is needed for this basis", session.path, "face.markers")
        from livebridge.face.builtin import builtin_markers

        markers = builtin_markers()
    else:
        markers = load_marker_set(session.markers)  # a file, or a shipped set by name ("builtin", "ict-68", ...)
    try:
        markers.check_mesh(len(basis.triangles))
    except InputError as error:
        raise InputError(error.message, session.path, "face.markers") from None
    return basis, markers


def _load_calibration(path: Path):
    from livebridge.calibration.calibfile import load_calibration

    return load_calibration(path)


def _session_url(url: str, session: Session, k: int) -> str:
    """A camera URL as the session means it: a relative ``replay://`` path or node ``key`` file is relative to
    the session file, and a simulated rig films the session's face (``[face]`` files) with the session's
    calibrated cameras (unless its URL names a calibration)."""
    from urllib.parse import parse_qs, quote, urlsplit

    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme == "replay" and session.path is not None:
        path = parts.netloc + parts.path if parts.netloc else parts.path
        if path and not Path(path).is_absolute():
            resolved = (session.path.parent / path).resolve()
            return f"replay://{resolved}" + (f"?{parts.query}" if parts.query else "")
    if scheme == "node" and session.path is not None:
        return _relative_key(url, parts, session.path.parent)
    if scheme != "sim":
        return url
    query = parse_qs(parts.query)
    named = [key for key in ("basis", "markers") if key in query]
    if named:
        raise InputError(f"the simulated rig films the session's face: name its {named[0]} in [face], "
                         f"not in the camera URL", session.path, f"cameras.urls[{k}]")
    options = [(key, value) for key, value in (("basis", session.basis), ("markers", session.markers))
               if isinstance(value, Path) or (key == "markers" and value not in (None, "builtin"))]  # or a name
    if session.calibration is not None and "calibration" not in query:
        options.append(("calibration", session.calibration))
    if not options:
        return url
    joiner = "&" if parts.query else "?"
    return url + joiner + "&".join(f"{key}={quote(str(value), safe='/')}" for key, value in options)


def _relative_key(url: str, parts, folder: Path) -> str:
    """A node URL's ``key`` file, when relative, relative to the session file's folder."""
    from urllib.parse import parse_qsl, quote, urlencode

    query = parse_qsl(parts.query, keep_blank_values=True)
    keys = [value for name, value in query if name == "key"]
    if len(keys) != 1 or not keys[0] or Path(keys[0]).is_absolute():
        return url  # none, or several (the URL parser names that error)
    resolved = str((folder / keys[0]).resolve())
    query = [(name, resolved if name == "key" else value) for name, value in query]
    return parts._replace(query=urlencode(query, quote_via=quote, safe="/")).geturl()


def open_session_cameras(session: Session):
    """Open every camera URL; returns ``(sources, cameras (CameraGroup), realtime)``.

    Cameras are matched to the session's calibration by name. Without a calibration file, each camera must
    know its own (:attr:`~livebridge.capture.sources.CameraSource.calibration`: a simulated rig's cameras,
    the calibration recorded with a take).
    """
    calibrated = _load_calibration(session.calibration) if session.calibration is not None else None
    sources = []
    try:
        for k, url in enumerate(session.camera_urls):
            sources += _open_url(session, k, url)
        cameras = _session_cameras(sources, calibrated, session)
        realtime = all(s.realtime for s in sources)
    except BaseException:
        stop_sources(sources)  # some (camera nodes) already talk to their device
        raise
    return sources, cameras, realtime


def _open_url(session: Session, k: int, url: str, expand: bool = True) -> list:
    """The sources of the session's ``k``-th camera URL (as the session means it, see :func:`_session_url`,
    unless not ``expand``); an error names ``cameras.urls[k]``."""
    expanded = _session_url(url, session, k) if expand else url
    try:
        return open_cameras(expanded)
    except InputError as error:
        if error.path in (None, url, expanded):  # about the URL itself: name it once
            inner = f"{error.field}: {error.message}" if error.field else error.message
        else:  # about a file the URL names (a calibration, a take)
            inner = str(error)
        raise InputError(f"{url}: {inner}", session.path, f"cameras.urls[{k}]") from None


def _session_cameras(sources, calibrated, session: Session):
    """The calibrated cameras of ``sources``: from the session's calibration by name, else their own."""
    from livebridge.calibration.cameras import CameraGroup

    if calibrated is not None:
        by_name = {c.name: c for c in calibrated.cameras}
        missing = [s.source_id for s in sources if s.source_id not in by_name]
        if missing:
            raise InputError(f"no calibration for camera {missing[0]!r} in {session.calibration}; calibrated: "
                             f"{', '.join(by_name)}", session.path, "calibration")
        cameras = CameraGroup([by_name[s.source_id] for s in sources])
        check_calibration_used(cameras, calibrated, session)
        return cameras
    own = [s.calibration for s in sources]
    unknown = [s.source_id for s, camera in zip(sources, own) if camera is None]
    if unknown:
        raise InputError(f"no calibration known for camera{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}: "
                         "give a calibration file (a camera node knows its camera's calibration only when the "
                         "node's own camera URL does, e.g. sim://rig, and once it answers)", session.path,
                         "calibration")
    return CameraGroup(own)


def _servo_rig(session: Session, muscle_names):
    """The session's servo rig: read from its file (checked against the face's muscles), or made in code."""
    from livebridge.servo.rig import load_rig

    if isinstance(session.servo_rig, Path):
        return load_rig(session.servo_rig, muscle_names)
    return session.servo_rig


def build_pipeline(session: Session, log=print, on_frame=None):
    """The pipeline a session describes, with every output opened (see the module docstring).

    The front follows the session's source: the marker front for cameras, :class:`~livebridge.arkit.front.
    LiveLinkFront` for a phone (``[source] kind = "livelinkface"``, its receiver bound here). ``on_frame`` is
    called on the outputs thread with every solved frame (see :class:`~livebridge.runtime.pipeline.Pipeline`).
    """
    from livebridge.runtime.pipeline import Pipeline

    basis, markers = load_face(session)
    model = _markerless_model(session, basis) if session.markerless is not None else None
    if model is None:
        check_markers(markers, basis, session)
    sources, cameras, realtime, fps = [], None, True, None  # a phone: no cameras
    opened = []
    try:
        if session.source.kind == "cameras":
            sources, cameras, realtime, fps = _session_sources(session, model, opened, log)
        front = _livelink_front(session, basis, markers, opened, log) if session.source.kind != "cameras" else None
        servo = None
        if session.servo_rig is not None:
            from livebridge.servo.output import ServoOutput

            log("set-up: configuring the servos")
            servo = ServoOutput(_servo_rig(session, basis.names), basis.names, log=log, poll_every=15)
            servo.configure()
            opened.append(lambda: servo.close(ease=False))
        render = None
        if session.render.enabled:
            from livebridge.output.render_server import RenderServer

            render = RenderServer(display_face(session, basis), markers, session.render.host, session.render.port,
                                  servo_names=servo.servo_names if servo is not None else (),
                                  allowed_origins=session.render.allowed_origins)
        outputs = _outputs(session, basis, opened)
        recorder = None
        if session.recording.enabled:
            from livebridge.take.recorder import TakeRecorder

            name = session.recording.take_name or f"take-{datetime.datetime.now().strftime('%Y%m%d-%H%M%S')}"
            directory = session.recording.directory / name
            if front is not None:  # a phone: its packets, no markers (the fps is the packets')
                recorder = TakeRecorder(directory, basis.names, (), session.path, record_displacements=False,
                                        phone=True)
            else:
                recorder = TakeRecorder(directory, basis.names, markers.names, session.path, session.calibration,
                                        fps=fps, record_frames=session.recording.raw_frames, cameras=cameras,
                                        lossless_frames=not realtime, frame_format=session.recording.frame_format)
            opened.append(recorder.close)
            sources = recorder.wrap_sources(sources)
            log(f"recording to {directory}" + (" (with raw frames)" if session.recording.raw_frames else ""))
        log("set-up: warming up the per-frame kernels (compiled on their first use)")
        if front is None and model is not None:
            from livebridge.markerless.front import MarkerlessFront

            front = MarkerlessFront(sources[0], model, 1.0 / fps, realtime, session.markerless.min_confidence)
        elif front is None:
            from livebridge.runtime.markers_front import MarkerFront

            front = MarkerFront(sources, cameras, basis, markers, 1.0 / fps, session.reconstruct, session.solver,
                                sync_tolerance=session.sync_tolerance, realtime=realtime,
                                labelling_timeout_s=session.labelling_timeout_s)
        return Pipeline(front, servo=servo, render=render, outputs=outputs, recorder=recorder, log=log,
                        on_frame=on_frame, status_interval=session.status_interval)
    except BaseException:
        for close in reversed(opened):
            close()
        raise


def _session_sources(session: Session, model, opened: list, log):
    """The session's cameras, opened and checked: ``(sources, cameras, realtime, fps)``; their stop is added
    to ``opened`` before any check (opened sources, camera nodes, may already talk to their devices)."""
    log(f"set-up: opening {len(session.camera_urls)} camera URL{'s' if len(session.camera_urls) > 1 else ''}")
    if model is None:
        sources, cameras, realtime = open_session_cameras(session)
    else:
        sources, cameras, realtime = _markerless_camera(session)
    opened.append(functools.partial(stop_sources, list(sources)))
    if model is None:
        check_cameras(cameras, session)
    fps = _fps(sources)
    _check_raw_frames(session, sources)
    return sources, cameras, realtime, fps


def _outputs(session: Session, basis, opened: list) -> list:
    """The session's other outputs (VMC, Live Link Face), opened; each one's close is added to ``opened``."""
    outputs = []
    if session.vmc.enabled:
        from livebridge.output.vmc import VMCOutput

        try:
            vmc = VMCOutput(basis.names, session.vmc.host, session.vmc.port, session.vmc.mapping, session.vmc.case)
        except InputError as error:
            raise InputError(error.message, session.path, f"outputs.vmc.{error.field}") from None
        opened.append(vmc.close)
        outputs.append(vmc)
    options = session.livelink
    if options.enabled:
        from livebridge.output.livelink import LiveLinkOutput

        try:  # the map is [outputs.vmc]'s: one muscle -> blendshape map, two transports
            livelink = LiveLinkOutput(basis.names, options.host, options.port, options.subject, options.device_id,
                                      session.vmc.mapping, options.fps)
        except InputError as error:
            field = "outputs.vmc.mapping" if error.field in (None, "mapping") else f"outputs.livelink.{error.field}"
            raise InputError(error.message, session.path, field) from None
        opened.append(livelink.close)
        outputs.append(livelink)
    return outputs


def load_arkit_shapes_for(session: Session, basis):
    """The session's ARKit shape set: its ``arkit_shapes`` file, else synthesised from the basis's muscles."""
    from livebridge.arkit.shapes import arkit_shapes_from_muscles, load_arkit_shapes

    path = session.source.arkit_shapes
    if path is None:
        return arkit_shapes_from_muscles(basis)
    try:
        return load_arkit_shapes(path, session.source.arkit_shapes_units)
    except InputError as error:
        inner = f"{error.field}: {error.message}" if error.field else error.message
        raise InputError(f"{path}: {inner}", session.path, "source.arkit_shapes") from None


def _livelink_front(session: Session, basis, markers, opened: list, log):
    """The phone's front: the receiver bound now (a taken port fails here) or the recorded phone take read and
    checked (``replay://``), then the ARKit solver for the face."""
    from livebridge.arkit.front import LiveLinkFront
    from livebridge.arkit.solve import ArkitSolver

    receiver = _phone_input(session, opened, log)
    try:
        solver = ArkitSolver(basis, markers, load_arkit_shapes_for(session, basis), session.solver)
    except InputError as error:
        if error.path is not None:
            raise
        raise InputError(error.message, session.path, "source.arkit_shapes") from None
    return LiveLinkFront(receiver, solver)


def _phone_input(session: Session, opened: list, log):
    """The phone's packets: a bound :class:`~livebridge.arkit.receiver.LiveLinkReceiver`, or a phone take played
    back (:class:`~livebridge.take.phone_replay.PhoneReplay`, for ``replay://`` URLs)."""
    from livebridge.arkit.receiver import LiveLinkReceiver
    from livebridge.take.phone_replay import SCHEME, open_phone_replay

    url = session.source.url
    if url.lower().startswith(f"{SCHEME}:"):
        try:
            replay = open_phone_replay(url)
        except InputError as error:
            if error.path is None or str(error.path) == url:  # about the URL itself
                raise InputError(f"{url}: {error.message}", session.path, "source.url") from None
            raise  # about the take's files: the error names the file and the field
        log(f"set-up: replaying the phone take {replay.path} ({len(replay.track.t)} packets)")
        return replay
    receiver = LiveLinkReceiver(url)
    try:
        receiver.open()
    except InputError as error:
        raise InputError(error.message, session.path, "source.url") from None
    opened.append(receiver.stop)
    log(f"set-up: listening for Live Link Face on {receiver.url}")
    return receiver


def _markerless_model(session: Session, basis):
    """The session's markerless model, checked against the basis's muscles and ``[markerless] head_rig``."""
    from livebridge.markerless.model import MarkerlessModel

    model = MarkerlessModel.load(session.markerless.model)
    if model.muscle_names != tuple(basis.names):
        raise InputError(f"the markerless model's muscles ({', '.join(model.muscle_names)}) are not the basis's "
                         f"({', '.join(basis.names)})", session.path, "markerless.model")
    rig = "none" if model.normalisation.head_rig is None else "leds"
    if session.markerless.head_rig not in (None, rig):
        raise InputError(f"the model was trained with head_rig = {rig!r}", session.path, "markerless.head_rig")
    return model


def _markerless_camera(session: Session):
    """The one camera of a markerless session: ``(sources, None, realtime)``."""
    url = session.camera_urls[0]
    # a simulated face video (sim://face) films a face of its own: it takes none of [face]'s options
    sources = _open_url(session, 0, url, expand=not url.startswith("sim://"))
    if len(sources) != 1:
        stop_sources(sources)
        raise InputError(f"markerless capture films with one camera, the URL opened {len(sources)}", session.path,
                         "cameras.urls[0]")
    return sources, None, bool(sources[0].realtime)


def _check_raw_frames(session: Session, sources) -> None:
    """Recording raw frames needs every camera's images: a camera node sends them only with ``images=full``."""
    if not (session.recording.enabled and session.recording.raw_frames):
        return
    blind = [s.source_id for s in sources if not s.capabilities.images]
    if blind:
        verb = "sends" if len(blind) == 1 else "send"
        raise InputError(f"raw frames are the cameras' images, but {', '.join(blind)} {verb}"
                         " only their markers' centroids (camera nodes): add images=full to their node:// URLs "
                         "(full frames over the network), or set raw_frames = false (the take still records the "
                         "markers and contractions)", session.path, "recording.raw_frames")


def _fps(sources) -> float:
    import math

    rates = [s.capabilities.fps for s in sources]
    rates = [r for r in rates if r and math.isfinite(r)]
    if not rates:
        raise InputError("the cameras do not report a frame rate; set fps in their URLs")
    return min(rates)

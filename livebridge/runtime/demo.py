"""``livebridge demo``: the whole pipeline on simulators, scored against their ground truth.

The demo is a :class:`~livebridge.runtime.session.Session` (:func:`demo_session`) run by the same
:func:`~livebridge.runtime.build.build_pipeline` as ``livebridge run``: the synthetic performer (built-in
face) is filmed by a simulated 4-camera rig (``sim://rig``); the frames go through the real pipeline
(detection, correspondence, labelling, solve) to a simulated Dynamixel bus on a pseudo-terminal driven by
the real driver, to the render client, and optionally to VMC and a recording.
:class:`~livebridge.simulators.score.GroundTruthScore` compares every solved frame with what the performer
did.

``livebridge demo --source livelinkface`` (:func:`build_livelink_demo`) replaces the rig with a simulated
iPhone running Live Link Face (:class:`~livebridge.simulators.iphone.SimulatedIPhone`, on its own thread,
real UDP packets over loopback at 60 Hz) heard by the session's ``[source] kind = "livelinkface"``
receiver; :class:`~livebridge.simulators.score.ContractionScore` compares every solved frame with the
contractions behind its packet.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlencode

from livebridge.runtime.session import RecordingOptions, RenderOptions, Session, SourceOptions, VMCOptions

DEMO_SERVO_URL = "simdynamixel://?ids=1-16&model=XL330-M288&process=1"  # the bus in its own process, as hardware


def _lead_in(realtime: bool, lead_in_s: float | None) -> float:
    """Default 2 s when paced (the first labelling may take a second on a busy machine), else 0."""
    return (2.0 if realtime else 0.0) if lead_in_s is None else float(lead_in_s)


@dataclass
class DemoParts:
    """What :func:`build_demo` made: the pipeline, its session and the score of its solved frames; ``phone``:
    the simulated iPhone of :func:`build_livelink_demo` (start it once the pipeline runs, stop it after)."""

    pipeline: object
    score: object
    session: Session
    phone: object = None


def demo_session(cameras: int = 4, seed: int = 1, fps: float = 60.0, size=(1280, 800), realtime: bool = True,
                 servo: bool = True, render: bool = True, host: str = "127.0.0.1", port: int = 8765,
                 vmc: tuple[str, int] | None = None, record=None, noise: float = 2.0, script: str = "mixed",
                 record_frames: bool = False, lead_in_s: float | None = None) -> Session:
    """The demo as a session (parameters as :func:`build_demo`'s)."""
    from livebridge.servo.rig import demo_rig

    lead_in_s = _lead_in(realtime, lead_in_s)
    width, height = size
    rig = {"cameras": cameras, "seed": seed, "fps": repr(float(fps)), "size": f"{width}x{height}",
           "noise": repr(float(noise)), "script": script, "lead_in_s": repr(lead_in_s), "realtime": int(realtime)}
    recording = RecordingOptions()
    if record is not None:
        record = Path(record)
        recording = RecordingOptions(True, record.parent, record_frames, take_name=record.name)
    return Session(None, (f"sim://rig?{urlencode(rig)}",), basis="builtin", markers="builtin",
                   servo_rig=demo_rig(DEMO_SERVO_URL) if servo else None,
                   render=RenderOptions(render, host, port),
                   vmc=VMCOptions(True, *vmc) if vmc is not None else VMCOptions(),
                   recording=recording)


def build_demo(cameras: int = 4, seed: int = 1, fps: float = 60.0, size=(1280, 800), realtime: bool = True,
               servo: bool = True, render: bool = True, host: str = "127.0.0.1", port: int = 8765,
               vmc: tuple[str, int] | None = None, record=None, noise: float = 2.0, script: str = "mixed",
               log=print, on_frame=None, record_frames: bool = False, lead_in_s: float | None = None) -> DemoParts:
    """Assemble the simulated demo pipeline (not started): :func:`demo_session` and
    :func:`~livebridge.runtime.build.build_pipeline`.

    Parameters
    ----------
    cameras : int
        Simulated cameras.
    seed : int
    fps : float
        Camera frame rate.
    size : (int, int)
        Image size of each simulated camera.
    realtime : bool
        Pace the cameras at ``fps``; False: as fast as the CPU allows (benchmarks, tests).
    servo : bool
        Drive 16 simulated Dynamixel servos (one per muscle) through the real driver.
    render : bool
        Serve the render page on ``host:port`` (0: any free port).
    vmc : (host, port), optional
        Also send VMC/OSC.
    record : Path, optional
        Record the take to this (new) directory (with the rig's calibration, ``calibration.toml``).
    record_frames : bool
        Also record the raw camera frames (replayable: ``replay://RECORD``).
    noise : float
        Sensor noise of the simulated cameras (grey levels).
    on_frame : callable, optional
        Also called with every solved frame.
    lead_in_s : float, optional
        The performer holds a still, neutral face this long before performing
        (:class:`~livebridge.simulators.lead_in.LeadIn`); default 2 s when ``realtime`` (the first labelling
        may take a second on a busy machine), else 0.
    """
    from livebridge.face.builtin import builtin_basis, builtin_markers
    from livebridge.runtime.build import build_pipeline
    from livebridge.simulators.lead_in import scripted_performer
    from livebridge.simulators.score import GroundTruthScore

    session = demo_session(cameras, seed, fps, size, realtime, servo, render, host, port, vmc, record, noise,
                           script, record_frames, lead_in_s)
    performer = scripted_performer(builtin_basis(), builtin_markers(), float(fps), seed, script,
                                   _lead_in(realtime, lead_in_s))  # the one the session's rig films
    score = GroundTruthScore(performer, skip=1)

    def both(frame):
        score(frame)
        if on_frame is not None:
            on_frame(frame)

    return DemoParts(build_pipeline(session, log=log, on_frame=both), score, session)


PHONE_NOISE = 0.02  # ARKit's frame-to-frame jitter on the weights, roughly (standard deviation)


def build_livelink_demo(seed: int = 1, script: str = "mixed", noise: float = PHONE_NOISE, servo: bool = True,
                        render: bool = True, host: str = "127.0.0.1", port: int = 8765,
                        vmc: tuple[str, int] | None = None, record=None, log=print, on_frame=None) -> DemoParts:
    """The Live Link Face demo (not started): a phone session on the built-in face, the receiver on a free
    loopback port, and the simulated iPhone that will send to it (``parts.phone``, not yet sending).

    Parameters
    ----------
    seed, script : the performer's (:class:`~livebridge.simulators.performer.ContractionScript`)
    noise : float
        Gaussian noise on the phone's weights (standard deviation).
    record : Path, optional
        Record the take (the solved contractions and the phone's packets) to this new folder.
    servo, render, host, port, vmc, log, on_frame : as :func:`build_demo`'s
    """
    from livebridge.runtime.build import build_pipeline
    from livebridge.servo.rig import demo_rig
    from livebridge.simulators.iphone import SimulatedIPhone
    from livebridge.simulators.score import ContractionScore

    session = Session(None, (), basis="builtin", markers="builtin",
                      servo_rig=demo_rig(DEMO_SERVO_URL) if servo else None,
                      render=RenderOptions(render, host, port),
                      vmc=VMCOptions(True, *vmc) if vmc is not None else VMCOptions(),
                      source=SourceOptions("livelinkface", "livelinkface://127.0.0.1:0"),
                      recording=RecordingOptions(True, Path(record).parent, take_name=Path(record).name)
                      if record is not None else RecordingOptions())
    score = None

    def both(frame):
        score(frame)
        if on_frame is not None:
            on_frame(frame)

    pipeline = build_pipeline(session, log=log, on_frame=both)
    receiver = pipeline.front.receiver
    phone = SimulatedIPhone(pipeline.front.muscle_names, *receiver.bound, script=script, seed=seed, noise=noise)
    score = ContractionScore(phone.truth)
    return DemoParts(pipeline, score, session, phone)


def build_markerless_demo(seed: int = 2, fps: float = 30.0, realtime: bool = True, servo: bool = True,
                          render: bool = True, host: str = "127.0.0.1", port: int = 8765, model=None,
                          log=print, on_frame=None) -> DemoParts:
    """The markerless demo (not started): a face filmed by one simulated camera with the LED head rig, light
    drifting +-20 % and the head turning +-10 degrees, analysed with ``model`` (a ``.npz``; default: trained
    first on a simulated training take of the same performer, seed 0) and sent through the same pipeline
    (simulated servo bus, render client) as ``livebridge run`` with a ``[markerless]`` session.

    The returned score is a :class:`~livebridge.markerless.simulated.MarkerlessScore` (contraction MAE).
    """
    import tempfile
    import time

    from livebridge.face.builtin import builtin_basis
    from livebridge.markerless.model import MarkerlessModel
    from livebridge.markerless.simulated import PERFORMER, MarkerlessScore, train_on_simulator
    from livebridge.runtime.build import build_pipeline
    from livebridge.runtime.session import MarkerlessOptions
    from livebridge.servo.rig import demo_rig

    basis = builtin_basis()
    if model is None:
        log("markerless demo: training on a simulated training take (isolated and combined gestures)")
        t0 = time.perf_counter()
        result, _ = train_on_simulator(basis, fps=fps, seed=0)
        model = Path(tempfile.mkdtemp(prefix="livebridge-markerless-")) / "model.npz"
        result.model.save(model)
        log(f"markerless demo: trained {len(result.model.regions)} regions in {time.perf_counter() - t0:.1f} s "
            f"-> {model}")
    MarkerlessModel.load(model)  # a bad file fails here, before anything opens
    query = urlencode({"script": "mixed", "seed": seed, "skin_seed": PERFORMER, "fps": repr(float(fps)),
                       "light_drift": 0.2, "head_turn": 10, "realtime": int(realtime)})
    session = Session(None, (f"sim://face?{query}",), basis="builtin", markers="builtin",
                      servo_rig=demo_rig(DEMO_SERVO_URL) if servo else None, render=RenderOptions(render, host, port),
                      markerless=MarkerlessOptions(Path(model), "leds"))
    parts = {}

    def both(frame):
        parts["score"](frame)
        if on_frame is not None:
            on_frame(frame)

    pipeline = build_pipeline(session, log=log, on_frame=both)
    parts["score"] = MarkerlessScore(pipeline.front.source)
    return DemoParts(pipeline, parts["score"], session)

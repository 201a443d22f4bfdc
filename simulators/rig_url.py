"""The ``sim://rig?...`` URL: a :class:`~livebridge.simulators.rig.SimRig` and its camera sources from the URL's
parameters, each checked against its range before anything is built (an error names the parameter)."""

from __future__ import annotations

import math
from dataclasses import replace

from livebridge.calibration.cameras import CameraGroup
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.shipped import load_marker_set
from livebridge.simulators.rig import (
    MAX_CAMERAS,
    MAX_SEED,
    RigConfig,
    SimCameraSource,
    SimRig,
    default_face,
    generate_markers,
)

_URL_KEYS = {"frames", "cameras", "seed", "fps", "noise", "drop", "jitter_ms", "spurious", "blur", "sync", "realtime",
             "size", "calibration", "script", "occlusion", "occlusion_rate", "diameter_mm", "basis", "markers",
             "lead_in_s", "camera", "t0"}


def rig_from_url(url: DeviceURL | str) -> SimRig:
    """A :class:`SimRig` from ``sim://rig?cameras=4&seed=1&fps=60&noise=2&drop=0.01&jitter_ms=0.5&spurious=0.1
    &blur=1&sync=hardware|free&size=1280x800&script=mixed&occlusion=1&occlusion_rate=0.05&diameter_mm=3
    &calibration=PATH&basis=PATH.npz&markers=PATH.toml&lead_in_s=2`` (``frames``, ``realtime``, ``camera`` and
    ``t0`` are the sources', see :func:`open_url`; ``lead_in_s``: the performer first holds a still, neutral face
    this long, :class:`~livebridge.simulators.lead_in.LeadIn`)."""
    from livebridge.simulators.lead_in import scripted_performer

    if isinstance(url, str):
        url = DeviceURL.parse(url)
    config, counts = _rig_options(url)
    if "basis" in url.query:
        basis = Basis.load(url.query["basis"])
        markers = load_marker_set(url.query["markers"]) if "markers" in url.query else generate_markers(basis)
    elif "markers" in url.query:  # the built-in face with these markers: no layout to design (seconds)
        from livebridge.face.builtin import builtin_basis

        basis, markers = builtin_basis(), load_marker_set(url.query["markers"])
    else:
        basis, markers = default_face()
    cameras = None
    if "calibration" in url.query:
        from livebridge.calibration.calibfile import load_calibration

        cameras = load_calibration(url.query["calibration"])
        cameras = getattr(cameras, "cameras", cameras) if not isinstance(cameras, CameraGroup) else cameras
        if "cameras" in url.query and len(cameras) != counts["cameras"]:
            raise InputError(f"cameras={counts['cameras']} but the calibration has {len(cameras)} cameras",
                             url.url, "cameras")
    performer = scripted_performer(basis, markers, config.fps, counts["seed"], counts["script"], counts["lead_in_s"])
    return SimRig(basis, markers, cameras=cameras, n_cameras=counts["cameras"], config=config, seed=counts["seed"],
                  performer=performer)


def _rig_options(url: DeviceURL) -> tuple[RigConfig, dict]:
    """The rig's configuration and its ``cameras``, ``seed``, ``script`` and ``frames`` from a ``sim://rig``
    URL, every value checked against its range before anything is built (an :class:`InputError` names the
    parameter and the range)."""
    from livebridge.simulators.performer import SCRIPTS

    if url.netloc != "rig":
        raise InputError(f"unknown simulator {url.netloc!r}; known: rig, face", url.url)
    url.check_known(_URL_KEYS)
    changes = {}
    for key, name, kind in (("fps", "fps", float), ("noise", "noise_sigma", float), ("drop", "drop_rate", float),
                            ("spurious", "spurious_rate", float), ("blur", "motion_blur", bool),
                            ("sync", "sync", str), ("occlusion", "occlusion", bool),
                            ("occlusion_rate", "occlusion_rate", float),
                            ("diameter_mm", "marker_diameter_mm", float)):
        value = url.take(key, kind)
        if value is not None:
            changes[name] = value
    if "jitter_ms" in url.query:
        jitter_ms = url.take("jitter_ms", float)
        if not 0.0 <= jitter_ms <= 1000.0:  # also refuses NaN
            raise InputError(f"jitter_ms must be a finite number in [0, 1000], got {jitter_ms}", url.url, "jitter_ms")
        changes["jitter_s"] = jitter_ms / 1000.0
    if "size" in url.query:
        try:
            width, height = (int(v) for v in url.query["size"].lower().split("x"))
        except ValueError:
            raise InputError("size must look like 1280x800", url.url, "size") from None
        changes["size"] = (width, height)
    counts = {"cameras": url.take("cameras", int, 4), "seed": url.take("seed", int, 0),
              "frames": url.take("frames", int), "script": url.query.get("script", "mixed")}
    for key, low, high in (("cameras", 1, MAX_CAMERAS), ("seed", 0, MAX_SEED), ("frames", 1, 10**9)):
        if counts[key] is not None and not low <= counts[key] <= high:
            raise InputError(f"{key} must be an integer in {low}..{high}, got {counts[key]}", url.url, key)
    counts["lead_in_s"] = url.take("lead_in_s", float, 0.0)
    if not 0.0 <= counts["lead_in_s"] <= 3600.0:  # also refuses NaN
        raise InputError(f"lead_in_s must be a number of seconds in [0, 3600], got {counts['lead_in_s']}", url.url,
                         "lead_in_s")
    if counts["script"] not in SCRIPTS:
        raise InputError(f"script must be one of {', '.join(SCRIPTS)}, got {counts['script']!r}", url.url, "script")
    try:
        config = replace(RigConfig(), **changes)
    except InputError as error:  # named by the URL's parameter, not the config field
        field = {"noise_sigma": "noise", "drop_rate": "drop", "spurious_rate": "spurious",
                 "marker_diameter_mm": "diameter_mm"}.get(error.field, error.field)
        raise InputError(error.message.replace(error.field, field, 1), url.url, field) from None
    return config, counts


def open_url(url: DeviceURL) -> list[SimCameraSource]:
    """The registry hook: one source per camera of the rig the URL describes (``frames=N``: the cameras end,
    like a finished take, after rig frame ``N - 1``; default: never). ``camera=K``: only camera ``K``, so
    several processes (camera nodes) can each film one camera of the same rig. ``t0=SECONDS``: frame 0 at
    that ``time.monotonic()`` time, which every process of one machine shares, so their paced cameras expose
    together. ``board=SPEC``: the rig films a calibration board instead
    (:func:`livebridge.simulators.board_render.open_board_url`)."""
    if "board" in url.query:
        from livebridge.simulators.board_render import open_board_url

        return open_board_url(url)
    realtime = url.take("realtime", bool, True)
    rig = rig_from_url(url)  # checks frames too, before building the rig
    sources = rig.sources(realtime=realtime)
    camera = url.take("camera", int, within=(0, rig.n_cameras - 1))
    if camera is not None:  # one camera of the shared rig (e.g. the one a camera node films)
        sources = [sources[camera]]
    t0 = url.take("t0", float)
    if t0 is not None:
        if not math.isfinite(t0):
            raise InputError(f"parameter 't0' must be a finite number of seconds, got {t0}", url.url, "t0")
        rig.start(t0)
    frames = url.take("frames", int)
    if frames is not None:
        for source in sources:
            source.n_frames = frames
    return sources

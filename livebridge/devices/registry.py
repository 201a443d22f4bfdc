"""The one registry of device URL schemes: camera sources and servo buses, real drivers and simulators alike.

The schemes are declared as plain data by their owners: the real drivers in :mod:`livebridge.drivers`,
the simulators in :mod:`livebridge.simulators` (``CAMERA_SCHEMES``, ``BUS_SCHEMES``); recorded takes
(``replay://``) and camera nodes (``node://``) are the registry's own. An implementation is named by a
``"module:attribute"`` string and imported only when its scheme is used, so opening a simulated rig never
imports a hardware SDK. The implementations import :mod:`livebridge.devices.url`, :mod:`livebridge.capture.sources` and
:mod:`livebridge.servo.bus`, never this module.

=========================================================  ==================================================
``v4l2:///dev/video0?width=1280&height=720&fps=60&fourcc=MJPG&exposure_us=2000&gain=0``  a V4L2 camera
``depthai://DEVICE_ID/CAM_B?fps=60&exposure_us=2000&iso=400``  one mono camera of an OAK (``DEVICE_ID`` may be
                                                           ``any``; no socket: both mono cameras)
``replay://PATH?realtime=0``                               a recorded take
``sim://rig?cameras=4&seed=1&fps=60&noise=2``              the simulated rig (one source per camera)
``node://HOST:PORT?camera=ID``                             one camera of a camera node (``livebridge node``):
                                                           its centroids, detected on the node, over ZeroMQ
``dynamixel:///dev/ttyUSB0?baud=1000000``                  a DYNAMIXEL Protocol 2.0 bus
``maestro:///dev/ttyACM0?device=12``                       a Pololu Maestro (``device``: Pololu protocol)
``ssc32:///dev/ttyUSB1?baud=115200``                       a Lynxmotion SSC-32U
``simdynamixel://?ids=1-16&model=XL330-M288&process=1``    simulated buses on a pseudo-terminal, driven by
``simmaestro://?channels=12``, ``simssc32://``             the real drivers (``process=1``: served from
                                                           their own process)
=========================================================  ==================================================

A parameter a scheme does not know, or one given twice, is an :class:`~livebridge.errors.InputError`
naming it (:class:`~livebridge.devices.url.DeviceURL`).
"""

from __future__ import annotations

import importlib
from functools import cache
from typing import TYPE_CHECKING

from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError

if TYPE_CHECKING:
    from livebridge.servo.bus import BusFacts, ServoBus

_OWN_CAMERA_SCHEMES = {"replay": "livebridge.take.replay:open_url", "node": "livebridge.nodes.source:open_url"}
_OWNERS = ("livebridge.drivers", "livebridge.simulators")


def _resolve(target: str):
    """The object a ``"module:attribute"`` string names (the module is imported now)."""
    module_name, attribute = target.split(":")
    return getattr(importlib.import_module(module_name), attribute)


def _merged(table: str, own: dict) -> dict:
    """Every owner's ``table`` (scheme -> entry) merged; a scheme declared twice is a programming error."""
    merged = dict(own)
    for owner in _OWNERS:
        for scheme, entry in getattr(importlib.import_module(owner), table).items():
            if scheme in merged:
                raise RuntimeError(f"URL scheme {scheme!r} is declared twice ({owner}.{table})")
            merged[scheme] = entry
    return merged


@cache
def camera_schemes() -> dict[str, str]:
    """Camera scheme -> ``"module:function"`` of its opener ``open_url(DeviceURL) -> list of sources``."""
    return _merged("CAMERA_SCHEMES", _OWN_CAMERA_SCHEMES)


@cache
def bus_schemes() -> dict[str, tuple[str, str]]:
    """Servo-bus scheme -> (``"module:function"`` of its opener ``open_url(DeviceURL, **options) -> bus``,
    ``"module:attribute"`` of the :class:`~livebridge.servo.bus.BusFacts` its driver declares)."""
    return _merged("BUS_SCHEMES", {})


def _entry(schemes: dict, url: DeviceURL, what: str):
    if url.scheme not in schemes:
        raise InputError(f"unknown {what} URL scheme {url.scheme!r}; known: {', '.join(sorted(schemes))}", url.url)
    return schemes[url.scheme]


def open_cameras(url: str) -> list:
    """Every camera source the URL names (a simulated rig or an OAK yields several), not started yet.

    Parameters
    ----------
    url : str
        See the module docstring.

    Returns
    -------
    list of CameraSource
    """
    parsed = DeviceURL.parse(url)
    return _resolve(_entry(camera_schemes(), parsed, "camera"))(parsed)


def open_camera(url: str):
    """The one camera source the URL names (raises when it names several, e.g. a whole simulated rig)."""
    sources = open_cameras(url)
    if len(sources) != 1:
        raise InputError(f"names {len(sources)} cameras; use open_cameras() or pick one camera", url)
    return sources[0]


def stop_sources(sources) -> None:
    """Stop every camera source, also when one of them fails to stop (the first such error is raised after).

    Safe on sources never started: opening one does not touch its device."""
    failure = None
    for source in sources:
        try:
            source.stop()
        except Exception as error:  # noqa: BLE001 - the others must still stop
            failure = failure or error
    if failure is not None:
        raise failure


def open_bus(url: str, **options) -> ServoBus:
    """Open the servo bus a URL names (the port opens now; servos are touched in ``configure``).

    ``options`` are the driver's keyword arguments (``log``, ``clock``, ``status_every``, ...).
    """
    parsed = DeviceURL.parse(url)
    opener, _ = _entry(bus_schemes(), parsed, "bus")
    return _resolve(opener)(parsed, **options)


def bus_facts(url: str) -> BusFacts:
    """What the driver of a bus URL's scheme declares about its device family (raw range, addresses, ...).

    Imports the driver module, not its SDK; opens nothing.
    """
    parsed = DeviceURL.parse(url)
    _, facts = _entry(bus_schemes(), parsed, "bus")
    return _resolve(facts)

"""The ``sim://`` camera scheme: ``sim://rig?...`` (the marker rig) and ``sim://face?...`` (the face video)."""

from __future__ import annotations

from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError

SIMULATORS = {"rig": "the marker camera rig", "face": "the face video with an LED head rig"}


def open_url(url: DeviceURL) -> list:
    """The registry hook: the sources of the simulator the URL's host names."""
    if url.netloc == "face":
        from livebridge.simulators.face_video import open_url as open_face

        return open_face(url)
    if url.netloc == "rig":
        from livebridge.simulators.rig_url import open_url as open_rig

        return open_rig(url)
    raise InputError(f"unknown simulator {url.netloc!r}; known: {', '.join(SIMULATORS)}", url.url)

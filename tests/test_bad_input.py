"""The bad-input corpus: malformed files through the real command line.

Every case writes a malformed input (generated here, never stored), runs the ``livebridge`` command that
reads it, and asserts what a user must see: a non-zero exit, exactly one ``Error:`` line that names the
file and the field (or what is wrong with the file), no traceback, no crash report (nothing was a bug),
and every file in the work folder left as it was (nothing written, nothing changed).

To cover another format, add a :class:`Format` (the command that reads it and its table of cases) to
:data:`FORMATS`; a case is a name, a function that writes the input, and the words the error must contain.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from factories import random_basis

from livebridge.cli import main


@dataclass(frozen=True)
class Case:
    """One malformed input.

    ``write(path)`` creates it (and may return something to ``close()`` after the command, such as a socket
    it holds); the error line must contain every word of ``expect``, and the input's file name unless the
    error is about a companion file the input points at (``names_input=False``, ``expect`` names that one).
    """

    name: str
    write: Callable[[Path], object]
    expect: tuple[str, ...] = ()
    names_input: bool = True


@dataclass(frozen=True)
class Format:
    """A file format: the file name, the command that reads it, the files it needs beside it, its cases."""

    name: str
    filename: str
    command: Callable[[Path, Path], list[str]]  # (input file, work folder) -> arguments of `livebridge`
    cases: tuple[Case, ...]
    setup: Callable[[Path], None] = lambda folder: None


def _text(text: str) -> Callable[[Path], None]:
    return _bytes(text.encode())


def _bytes(data: bytes) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        path.write_bytes(data)
    return write


def _nothing(path: Path) -> None:
    pass


def _directory(path: Path) -> None:
    path.mkdir()


def _unreadable(path: Path) -> None:
    if os.geteuid() == 0:
        pytest.skip("root reads files without read permission")
    path.write_text("x = 1\n")
    path.chmod(0)


def _common_cases(missing: str = "file not found", directory: str = "is a directory") -> tuple[Case, ...]:
    """What can go wrong with any file, whatever its format."""
    return (
        Case("missing", _nothing, (missing,)),
        Case("directory", _directory, (directory,)),
        Case("unreadable", _unreadable, ("permission denied",)),
    )


def _toml_cases(**common) -> tuple[Case, ...]:
    return _common_cases(**common) + (
        Case("not utf-8", _bytes(b"x = \"\xff\xfe\"\n"), ("not UTF-8",)),
        Case("binary", _bytes(bytes(range(256))), ("not UTF-8",)),
        Case("bad toml", _text("[cameras\nurls = \n"), ("not valid TOML",)),
        Case("duplicate key", _text("a = 1\na = 2\n"), ("not valid TOML",)),
    )


# ------------------------------------------------------------------------------------------------ basis .npz
_BASIS = random_basis(np.random.default_rng(0), n_vertices=25, n_muscles=2)
_MANIFEST = {"format": "livebridge-basis", "version": 1, "units": "mm",
             "muscles": [{"name": "m0", "region": "upper", "side": None, "description": ""},
                         {"name": "m1", "region": "lower", "side": None, "description": ""}]}


def _npz(**changes) -> Callable[[Path], None]:
    """A basis file with some arrays replaced (``None``: left out); ``manifest=dict`` is written as JSON."""
    def write(path: Path) -> None:
        arrays = {"manifest": np.array(json.dumps(_MANIFEST)), "neutral": _BASIS.neutral,
                  "triangles": _BASIS.triangles.astype(np.int32), "elements": _BASIS.elements}
        for key, value in changes.items():
            if value is None:
                arrays.pop(key)
            else:
                arrays[key] = np.array(json.dumps(value)) if isinstance(value, (dict, list)) else value
        with path.open("wb") as stream:
            np.savez(stream, **arrays)
    return write


def _manifest(**changes) -> Callable[[Path], None]:
    return _npz(manifest={**_MANIFEST, **changes})


def _muscle(**changes) -> Callable[[Path], None]:
    return _manifest(muscles=[{**_MANIFEST["muscles"][0], **changes}, _MANIFEST["muscles"][1]])


def _damaged(cut: Callable[[bytes], bytes]) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        _npz()(path)
        path.write_bytes(cut(path.read_bytes()))
    return write


def _flip_inside_first_array(data: bytes) -> bytes:
    start = data.index(b"\x93NUMPY") + 200  # inside the first member's array data
    return data[:start] + bytes([data[start] ^ 0xFF]) + data[start + 1:]


def _npy(path: Path) -> None:
    with path.open("wb") as stream:
        np.save(stream, _BASIS.neutral)


def _neutral_with(value) -> Callable[[Path], None]:
    neutral = _BASIS.neutral.copy()
    neutral[3, 1] = value
    return _npz(neutral=neutral)


BASIS_CASES = _common_cases() + (
    Case("empty file", _bytes(b""), ("not a livebridge basis",)),
    Case("text file", _text("neutral = 1\n"), ("not a livebridge basis", "not a zip archive")),
    Case("truncated", _damaged(lambda data: data[:len(data) // 2]), ("not a livebridge basis",)),
    Case("one byte short", _damaged(lambda data: data[:-1]), ("not a livebridge basis",)),
    Case("bit flip in an array", _damaged(_flip_inside_first_array), ("damaged",)),
    Case("a .npy array", _npy, (".npy",)),
    Case("manifest missing", _npz(manifest=None), ("manifest",)),
    Case("elements missing", _npz(elements=None), ("elements",)),
    Case("manifest not JSON", _npz(manifest=np.array("{format: basis")), ("manifest", "JSON")),
    Case("manifest a JSON list", _npz(manifest=np.array("[1, 2]")), ("manifest", "object")),
    Case("manifest a JSON string", _npz(manifest=np.array('"basis"')), ("manifest", "object")),
    Case("manifest numbers", _npz(manifest=np.arange(3)), ("manifest",)),
    Case("manifest pickled", _npz(manifest=np.array([{"a": 1}], dtype=object)), ("manifest",)),
    Case("wrong format", _manifest(format="livebridge-markers"), ("format",)),
    Case("version a string", _manifest(version="1"), ("version",)),
    Case("version from the future", _manifest(version=99), ("version", "newer")),
    Case("units in cm", _manifest(units="cm"), ("units",)),
    Case("no muscles", _manifest(muscles=[]), ("muscles",)),
    Case("muscles missing", _npz(manifest={k: v for k, v in _MANIFEST.items() if k != "muscles"}), ("muscles",)),
    Case("muscles an object", _manifest(muscles={"m0": "upper"}), ("muscles",)),
    Case("muscle a string", _manifest(muscles=["m0", "m1"]), ("muscles[0]",)),
    Case("muscle without region", _npz(manifest={**_MANIFEST, "muscles": [{"name": "m0"}, _MANIFEST["muscles"][1]]}),
         ("muscles[0].region", "missing")),
    Case("muscle region unknown", _muscle(region="middle"), ("muscles[0]", "region")),
    Case("muscle region a number", _muscle(region=1), ("muscles[0].region",)),
    Case("muscle name a number", _muscle(name=5), ("muscles[0].name",)),
    Case("muscle name empty", _muscle(name=""), ("muscles[0].name",)),
    Case("muscle side unknown", _muscle(side="X"), ("muscles[0]", "side")),
    Case("muscle names repeat", _muscle(name="m1"), ("muscles", "repeat")),
    Case("neutral text", _npz(neutral=_BASIS.neutral.astype(str)), ("neutral", "numbers")),
    Case("neutral booleans", _npz(neutral=_BASIS.neutral > 0), ("neutral", "numbers")),
    Case("neutral complex", _npz(neutral=_BASIS.neutral + 1j), ("neutral", "numbers")),
    Case("neutral pickled", _npz(neutral=np.array([None, 1], dtype=object)), ("neutral",)),
    Case("neutral 2D points", _npz(neutral=_BASIS.neutral[:, :2]), ("neutral", "shape")),
    Case("neutral a scalar", _npz(neutral=np.float64(1)), ("neutral", "shape")),
    Case("neutral NaN", _neutral_with(np.nan), ("neutral", "NaN")),
    Case("neutral infinite", _neutral_with(np.inf), ("neutral", "NaN")),
    Case("elements infinite", _npz(elements=np.where(_BASIS.elements > 1, np.inf, _BASIS.elements)),
         ("elements", "NaN")),
    Case("elements of 3 muscles", _npz(elements=np.zeros((3, 25, 3))), ("elements", "shape")),
    Case("elements of other vertices", _npz(elements=np.zeros((2, 24, 3))), ("elements", "shape")),
    Case("triangles fractional", _npz(triangles=_BASIS.triangles + 0.5), ("triangles", "whole numbers")),
    Case("triangles past the vertices", _npz(triangles=_BASIS.triangles + 25), ("triangles", "do not exist")),
    Case("triangles negative", _npz(triangles=_BASIS.triangles - 1), ("triangles", "do not exist")),
    Case("triangles huge unsigned", _npz(triangles=_BASIS.triangles.astype(np.uint64) + np.uint64(2**63)),
         ("triangles",)),
    Case("triangles of 4 corners", _npz(triangles=np.zeros((5, 4), np.int32)), ("triangles", "shape")),
)


def _write_basis(folder: Path) -> None:
    _npz()(folder / "basis.npz")


# ------------------------------------------------------------------------------------------------ markers .toml
_MARKER = {"name": '"a"', "triangle": "3", "barycentric": "[0.2, 0.3, 0.5]", "region": '"upper"', "role": '"face"'}
_HEADER = 'format = "livebridge-markers"\nversion = 1\n'


def _markers(header: str = _HEADER, **changes) -> Callable[[Path], None]:
    """A marker file whose first marker has some keys changed (``None``: left out)."""
    first = {**_MARKER, **changes}
    rows = [first, {**_MARKER, "name": '"b"', "barycentric": "[0.5, 0.3, 0.2]"}]
    body = "".join("[[marker]]\n" + "".join(f"{k} = {v}\n" for k, v in row.items() if v is not None) for row in rows)
    return _text(header + body)


MARKER_CASES = _toml_cases() + (
    Case("empty file", _text(""), ("format",)),
    Case("wrong format", _markers('format = "livebridge-basis"\nversion = 1\n'), ("format",)),
    Case("version a string", _markers('format = "livebridge-markers"\nversion = "1"\n'), ("version",)),
    Case("version from the future", _markers('format = "livebridge-markers"\nversion = 7\n'), ("version", "newer")),
    Case("unknown top-level key", _markers(_HEADER + "markers_per_region = 3\n"), ("markers_per_region", "unknown")),
    Case("no markers", _text(_HEADER), ("marker", "missing")),
    Case("two markers at one place", _markers(barycentric="[0.5, 0.3, 0.2]"), ("'a'", "'b'", "same place")),
    Case("empty marker list", _text(_HEADER + "marker = []\n"), ("marker", "no markers")),
    Case("marker a number", _text(_HEADER + "marker = 5\n"), ("marker",)),
    Case("marker a list of names", _text(_HEADER + 'marker = ["a", "b"]\n'), ("marker[0]",)),
    Case("unknown marker key", _markers(triangel="3"), ("marker[0].triangel", "unknown")),
    Case("name missing", _markers(name=None), ("marker[0].name", "missing")),
    Case("name a number", _markers(name="5"), ("marker[0].name",)),
    Case("triangle a string", _markers(triangle='"3"'), ("marker[0].triangle",)),
    Case("triangle fractional", _markers(triangle="1.5"), ("marker[0].triangle",)),
    Case("triangle a boolean", _markers(triangle="true"), ("marker[0].triangle",)),
    Case("triangle negative", _markers(triangle="-1"), ("marker[0].triangle",)),
    Case("triangle not on the mesh", _markers(triangle="99999"), ("marker a", "does not exist")),
    Case("triangle missing", _markers(triangle=None), ("marker[0].triangle", "missing")),
    Case("barycentric strings", _markers(barycentric='["0.2", "0.3", "0.5"]'), ("marker[0].barycentric",)),
    Case("barycentric two values", _markers(barycentric="[0.5, 0.5]"), ("marker[0].barycentric",)),
    Case("barycentric a number", _markers(barycentric="1.0"), ("marker[0].barycentric",)),
    Case("barycentric nested", _markers(barycentric="[[0.2], [0.3], [0.5]]"), ("marker[0].barycentric",)),
    Case("barycentric NaN", _markers(barycentric="[nan, 0.5, 0.5]"), ("marker a", "barycentric")),
    Case("barycentric infinite", _markers(barycentric="[inf, 0.0, 0.0]"), ("marker a", "barycentric")),
    Case("barycentric negative", _markers(barycentric="[-0.5, 1.0, 0.5]"), ("marker a", "barycentric")),
    Case("barycentric not summing to 1", _markers(barycentric="[0.2, 0.2, 0.2]"), ("marker a", "barycentric")),
    Case("region unknown", _markers(region='"middle"'), ("marker a", "region")),
    Case("region a number", _markers(region="1"), ("marker[0].region",)),
    Case("role unknown", _markers(role='"tail"'), ("marker a", "role")),
    Case("role a number", _markers(role="1"), ("marker[0].role",)),
    Case("names repeat", _markers(name='"b"'), ("names", "repeat")),
)


# ------------------------------------------------------------------------------------------------ calibration .toml
_CAMERA = {"name": '"cam0"', "size": "[640, 480]", "matrix": "[[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0, 0, 1]]",
           "distortions": "[0.0, 0.0, 0.0, 0.0, 0.0]", "rotation": "[0.0, 0.1, 0.0]",
           "translation": "[10.0, 0.0, 500.0]"}


def _calibration(extra: str = "", **changes) -> Callable[[Path], None]:
    """A two-camera calibration whose first camera has some keys changed (``None``: left out)."""
    first = {**_CAMERA, **changes}
    second = {**_CAMERA, "name": '"cam1"'}
    tables = [f"[cam_{i}]\n" + "".join(f"{k} = {v}\n" for k, v in cam.items() if v is not None)
              for i, cam in enumerate((first, second))]
    return _text("\n".join(tables) + extra)


CALIBRATION_CASES = _toml_cases() + (
    Case("empty file", _text(""), ("no [cam_N] tables",)),
    Case("rotation 1e308", _calibration(rotation="[1e308, 0.0, 0.0]"), ("cam_0.rotation",)),
    Case("rotation beyond one turn", _calibration(rotation="[0.0, 0.0, 7.0]"), ("cam_0.rotation",)),
    Case("rotation NaN", _calibration(rotation="[nan, 0.0, 0.0]"), ("cam_0.rotation", "NaN")),
    Case("rotation infinite", _calibration(rotation="[0.0, -inf, 0.0]"), ("cam_0.rotation",)),
    Case("rotation text", _calibration(rotation='["x", 0, 0]'), ("cam_0.rotation",)),
    Case("rotation of 2 values", _calibration(rotation="[0.0, 0.1]"), ("cam_0.rotation", "shape")),
    Case("translation 1e309", _calibration(translation="[1e309, 0.0, 0.0]"), ("cam_0.translation",)),
    Case("translation missing", _calibration(translation=None), ("cam_0.translation", "missing")),
    Case("typo fishey", _calibration(fishey="true"), ("cam_0.fishey", "unknown")),
    Case("fisheye a string", _calibration(fisheye='"yes"'), ("cam_0.fisheye",)),
    Case("name missing", _calibration(name=None), ("cam_0.name", "missing")),
    Case("name a list", _calibration(name="[1]"), ("cam_0.name",)),
    Case("names repeat", _calibration(name='"cam1"'), ("cam_1.name", "twice")),
    Case("size zero", _calibration(size="[0, 480]"), ("cam_0.size",)),
    Case("size fractional", _calibration(size="[640.5, 480]"), ("cam_0.size",)),
    Case("size text", _calibration(size='["640", "480"]'), ("cam_0.size",)),
    Case("size one number", _calibration(size="640"), ("cam_0.size",)),
    Case("matrix 2x2", _calibration(matrix="[[1, 0], [0, 1]]"), ("cam_0.matrix",)),
    Case("matrix ragged", _calibration(matrix="[[1, 0, 0], [0, 1], [0, 0, 1]]"), ("cam_0.matrix",)),
    Case("matrix negative focal", _calibration(matrix="[[-500.0, 0, 320], [0, 500, 240], [0, 0, 1]]"),
         ("cam_0.matrix",)),
    Case("matrix last row", _calibration(matrix="[[500.0, 0, 320], [0, 500, 240], [0, 1, 1]]"), ("cam_0.matrix",)),
    Case("distortions 9 values", _calibration(distortions="[0, 0, 0, 0, 0, 0, 0, 0, 0]"), ("cam_0.distortions",)),
    Case("distortions empty", _calibration(distortions="[]"), ("cam_0.distortions",)),
    Case("distortions rational terms", _calibration(distortions="[0, 0, 0, 0, 0, 0.1, 0, 0]"),
         ("cam_0.distortions",)),
    Case("camera table a number", _text("cam_0 = 5\n"), ("cam_0",)),
    Case("table with another name", _text("[camera]\nname = 'a'\n"), ("camera",)),
    Case("metadata a number", _calibration("metadata = 5\n"), ("metadata",)),
    Case("metadata rms a string", _calibration('[metadata]\nrms_px = "low"\n'), ("metadata.rms_px",)),
    Case("metadata rms negative", _calibration("[metadata.rms_px]\ncam0 = -1.0\n"), ("metadata.rms_px.cam0",)),
    Case("metadata rms NaN", _calibration("[metadata.rms_px]\ncam0 = nan\n"), ("metadata.rms_px.cam0",)),
    Case("metadata world frame a number", _calibration("[metadata]\nworld_frame = 5\n"), ("metadata.world_frame",)),
)


# ------------------------------------------------------------------------------------------------ session .toml
_SIM = '[cameras]\nurls = ["sim://rig?cameras=2&realtime=0&size=160x100"]\n'


def _session(extra: str, top: str = "") -> Callable[[Path], None]:
    return _text(top + _SIM + extra)


def _session_with_bad(name: str, write: Callable[[Path], None], text: str) -> Callable[[Path], None]:
    """A session that points at a malformed companion file ``name``."""
    def write_both(path: Path) -> None:
        write(path.parent / name)
        path.write_text(text)
    return write_both


# A Live Link Face session ([source] kind = "livelinkface"): no cameras; the render client off, so that nothing
# but the case's own fault can stop it.
_PHONE = '[source]\nkind = "livelinkface"\n'
_PHONE_TAIL = "[outputs.render]\nenabled = false\n"


def _phone(source_keys: str, companion: str | None = None) -> Callable[[Path], None]:
    """A phone session with more ``[source]`` keys (and an empty companion file of that name beside it)."""
    def write(path: Path) -> None:
        if companion is not None:
            (path.parent / companion).write_bytes(b"not an npz")
        path.write_text(_PHONE + source_keys + _PHONE_TAIL)
    return write


def _phone_shapes(names=("jawOpen",), vertices=None, value=0.1) -> Callable[[Path], None]:
    """A phone session whose ARKit shapes (``shapes.npz``) are malformed."""
    def write(path: Path) -> None:
        from livebridge.face.builtin import builtin_basis

        n = builtin_basis().n_vertices if vertices is None else vertices
        np.savez(path.parent / "shapes.npz", names=np.array(names), deltas=np.full((len(names), n, 3), value))
        path.write_text(_PHONE + 'arkit_shapes = "shapes.npz"\n' + _PHONE_TAIL)
    return write


def _phone_port_in_use(path: Path):
    import socket

    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    path.write_text(_PHONE + f'url = "livelinkface://127.0.0.1:{busy.getsockname()[1]}"\n' + _PHONE_TAIL)
    return busy  # held until the command has run


def _render_port_in_use(path: Path):
    import socket

    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    path.write_text(_SIM + f"[outputs.render]\nport = {busy.getsockname()[1]}\n")
    return busy  # held until the command has run


SESSION_CASES = _toml_cases() + (
    Case("empty file", _text(""), ("cameras.urls", "missing")),
    Case("unknown top-level key", _session("", top="calibraton = 'x.toml'\n"), ("calibraton",)),
    Case("unknown table", _session("[camera]\nurls = []\n"), ("camera",)),
    Case("no camera URLs", _text("[cameras]\nurls = []\n"), ("cameras.urls",)),
    Case("camera URL a number", _text("[cameras]\nurls = [5]\n"), ("cameras.urls",)),
    Case("camera URL without scheme", _text('[cameras]\nurls = ["webcam0"]\n'), ("cameras.urls",)),
    Case("sync tolerance text", _text('[cameras]\nurls = ["sim://rig"]\nsync_tolerance = "half"\n'),
         ("cameras.sync_tolerance",)),
    Case("real cameras without calibration", _text('[cameras]\nurls = ["v4l2:///dev/video0"]\n'), ("calibration",)),
    Case("calibration missing", _session("", top='calibration = "nowhere.toml"\n'), ("calibration", "not found")),
    Case("basis missing", _session('[face]\nbasis = "nowhere.npz"\n'), ("face.basis", "not found")),
    Case("basis not .npz", _session('[face]\nbasis = "."\n'), ("face.basis",)),
    Case("markers missing", _session('[face]\nmarkers = "nowhere.toml"\n'), ("face.markers", "not found")),
    Case("display mode unknown", _session('[face]\ndisplay_mode = "sideways"\n'),
         ("face.display_mode", "sideways", "beside")),
    Case("display mode not text", _session("[face]\ndisplay_mode = 2\n"), ("face.display_mode",)),
    Case("display missing", _session('[face]\ndisplay = "nowhere.npz"\n'), ("face.display", "not found")),
    Case("display not .npz", _session('[face]\ndisplay = "."\n'), ("face.display", ".npz")),
    Case("solver mode unknown", _session('[solver]\nmode = "fast"\n'), ("solver.mode",)),
    Case("solver sweeps text", _session('[solver]\nsweeps = "two"\n'), ("solver.sweeps",)),
    Case("reconstruct tolerance NaN", _session("[reconstruct]\ntolerance_px = nan\n"), ("reconstruct.tolerance_px",)),
    Case("render port 70000", _session("[outputs.render]\nport = 70000\n"), ("outputs.render.port",)),
    Case("render port negative", _session("[outputs.render]\nport = -1\n"), ("outputs.render.port",)),
    Case("render enabled text", _session('[outputs.render]\nenabled = "yes"\n'), ("outputs.render.enabled",)),
    Case("render host a number", _session("[outputs.render]\nhost = 127\n"), ("outputs.render.host",)),
    Case("render foreign origin", _session('[outputs.render]\nallowed_origins = ["evil.example"]\n'),
         ("outputs.render.allowed_origins[0]",)),
    Case("render port in use", _render_port_in_use,
         ("outputs.render.port", "render server 127.0.0.1:", "address already in use")),
    Case("render host not local", _session('[outputs.render]\nhost = "0.0.0.0"\n'),
         ("outputs.render.host", "not a loopback address", "--allow-remote")),
    Case("render host not on this machine", _session('[outputs.render]\nhost = "203.0.113.7"\n'),
         ("outputs.render.host",)),
    Case("vmc case unknown", _session('[outputs.vmc]\ncase = "SHOUT"\n'), ("outputs.vmc.case",)),
    Case("vmc mapping unknown", _session('[outputs.vmc]\nmapping = "arkit"\n'), ("outputs.vmc.mapping",)),
    Case("vmc port 99999", _session("[outputs.vmc]\nport = 99999\n"), ("outputs.vmc.port",)),
    Case("vmc port 0", _session("[outputs.vmc]\nenabled = true\nport = 0\n"), ("outputs.vmc.port", "1..65535")),
    Case("vmc host broadcast", _session('[outputs.vmc]\nenabled = true\nhost = "255.255.255.255"\n'),
         ("outputs.vmc.host",)),
    Case("livelink port 0", _session("[outputs.livelink]\nport = 0\n"), ("outputs.livelink.port", "1..65535")),
    Case("livelink port text", _session('[outputs.livelink]\nport = "11111"\n'), ("outputs.livelink.port",)),
    Case("livelink empty subject", _session('[outputs.livelink]\nsubject = ""\n'), ("outputs.livelink.subject",)),
    Case("livelink long device id", _session(f'[outputs.livelink]\ndevice_id = "{"x" * 300}"\n'),
         ("outputs.livelink.device_id", "256 bytes")),
    Case("livelink fps 0", _session("[outputs.livelink]\nfps = 0\n"), ("outputs.livelink.fps",)),
    Case("livelink unknown key", _session("[outputs.livelink]\nsubjct = 1\n"), ("outputs.livelink.subjct",)),
    Case("source kind unknown", _session('[source]\nkind = "iphone"\n'), ("source.kind", "livelinkface")),
    Case("source url for cameras", _session('[source]\nurl = "livelinkface://"\n'), ("source.url", "unknown")),
    Case("livelinkface with cameras", _session(_PHONE), ("cameras", "livelinkface")),
    Case("livelinkface with calibration", _text('calibration = "c.toml"\n' + _PHONE), ("calibration",)),
    *(Case(f"livelinkface url {name}", _phone(f'url = "{url}"\n'), ("source.url", *words))
      for name, url, words in (
          ("other scheme", "udp://127.0.0.1:11111", ("livelinkface://",)),
          ("port too big", "livelinkface://127.0.0.1:99999", ("0..65535",)),
          ("port text", "livelinkface://127.0.0.1:abc", ("abc",)),
          ("a path", "livelinkface://127.0.0.1:11111/face", ("/face",)),
          ("a host name", "livelinkface://phone.local:11111", ("phone.local", "IP address")),
          ("unknown parameter", "livelinkface://:11111?devcie=A", ("devcie",)),
          ("empty device", "livelinkface://:11111?device=", ("device",)),
          ("not a URL", "11111", ()))),
    Case("livelinkface url not text", _phone("url = 11111\n"), ("source.url", "str")),
    Case("livelinkface port in use", _phone_port_in_use, ("source.url", "cannot listen")),
    Case("livelinkface shapes missing", _phone('arkit_shapes = "nothing.npz"\n'),
         ("source.arkit_shapes", "file not found")),
    Case("livelinkface shapes not npz", _phone('arkit_shapes = "shapes.txt"\n', "shapes.txt"),
         ("source.arkit_shapes", ".npz")),
    Case("livelinkface shapes units", _phone('arkit_shapes_units = "inch"\n'),
         ("source.arkit_shapes_units", "inch")),
    Case("livelinkface replay without a take", _phone('url = "replay://"\n'), ("source.url", "take folder")),
    Case("livelinkface replay unknown parameter", _phone('url = "replay://take?speed=2"\n'),
         ("source.url", "speed")),
    Case("livelinkface replay of a missing take", _phone('url = "replay://nowhere"\n'),
         ("nowhere", "no such take directory"), names_input=False),
    Case("livelinkface raw frames", _text(_PHONE + '[recording]\nenabled = true\ndirectory = "takes"\n'
                                          "raw_frames = true\n"), ("recording.raw_frames", "camera images")),
    Case("livelinkface shapes not ARKit names", _phone_shapes(names=["smile"]),
         ("source.arkit_shapes", "shapes.npz", "smile")),
    Case("livelinkface shapes on another mesh", _phone_shapes(vertices=5),
         ("source.arkit_shapes", "vertices")),
    Case("livelinkface shapes NaN", _phone_shapes(value=float("nan")), ("source.arkit_shapes", "NaN")),
    Case("livelinkface shapes not an npz", _phone('arkit_shapes = "shapes.npz"\n', "shapes.npz"),
         ("source.arkit_shapes", "shapes.npz")),
    Case("unknown output", _session("[outputs.osc]\nport = 1\n"), ("outputs.osc",)),
    Case("recording without folder", _session("[recording]\nenabled = true\n"), ("recording.directory",)),
    Case("recording format", _session('[recording]\nframe_format = "jpg"\n'), ("recording.frame_format",)),
    Case("frames negative", _session("[runtime]\nframes = -3\n"), ("runtime.frames",)),
    Case("status interval zero", _session("[runtime]\nstatus_interval = 0\n"), ("runtime.status_interval",)),
    Case("status interval NaN", _session("[runtime]\nstatus_interval = nan\n"), ("runtime.status_interval",)),
    Case("labelling timeout negative", _session("[runtime]\nlabelling_timeout_s = -1\n"),
         ("runtime.labelling_timeout_s",)),
    Case("labelling timeout NaN", _session("[runtime]\nlabelling_timeout_s = nan\n"),
         ("runtime.labelling_timeout_s",)),
    Case("labelling timeout text", _session('[runtime]\nlabelling_timeout_s = "10 s"\n'),
         ("runtime.labelling_timeout_s",)),
    Case("a marker set of two markers", _session_with_bad("m.toml", _markers(), _SIM + '[face]\nmarkers = "m.toml"\n'),
         ("face.markers", "2 markers", "4 or more")),
    Case("a calibration of cameras at one place", _session_with_bad("rig.toml", _calibration(),
                                                                    'calibration = "rig.toml"\n' + _SIM),
         ("calibration", "all at one place")),
    Case("a damaged basis", _session_with_bad("face.npz", _damaged(lambda data: data[:100]),
                                              _SIM + '[face]\nbasis = "face.npz"\nmarkers = "builtin"\n'),
         ("face.npz", "not a livebridge basis"), names_input=False),
    Case("a marker set with an empty list", _session_with_bad("m.toml", _text(_HEADER + "marker = []\n"),
                                                              _SIM + '[face]\nmarkers = "m.toml"\n'),
         ("m.toml", "marker"), names_input=False),
    *[Case(f"node URL {name}", _text(f'[cameras]\nurls = ["node://{url}"]\n'), ("cameras.urls[0]", *words))
      for name, url, words in (
          ("without a camera", "127.0.0.1:7000", ("camera=ID",)),
          ("port 65535", "127.0.0.1:65535?camera=cam0", ("1..65534",)),
          ("without a port", "127.0.0.1?camera=cam0", ("HOST:PORT",)),
          ("images unknown", "127.0.0.1:7000?camera=cam0&images=jpeg", ("images", "jpeg")),
          ("unknown parameter", "127.0.0.1:7000?camera=cam0&fps=30", ("fps",)),
          ("dead_after_s zero", "127.0.0.1:7000?camera=cam0&dead_after_s=0", ("dead_after_s",)),
          ("realtime text", "127.0.0.1:7000?camera=cam0&realtime=maybe", ("realtime",)),
          ("key file missing", "127.0.0.1:7000?camera=cam0&key=nowhere.key", ("nowhere.key", "cannot read")))],
    Case("node URL key file too short", _session_with_bad(
        "short.key", _bytes(b"x" * 8), '[cameras]\nurls = ["node://127.0.0.1:7000?camera=cam0&key=short.key"]\n'),
         ("cameras.urls[0]", "short.key", "at least 32 bytes")),
    Case("a node that does not answer, no calibration file",
         _text('[cameras]\nurls = ["node://127.0.0.1:9?camera=cam0&dead_after_s=0.05"]\n'),
         ("calibration", "no calibration known for camera cam0")),
    Case("a calibration with 1e308", _session_with_bad("rig.toml", _calibration(rotation="[1e308, 0, 0]"),
                                                       'calibration = "rig.toml"\n' + _SIM),
         ("rig.toml", "cam_0.rotation"), names_input=False),
)



# ------------------------------------------------------------------------------------------------ contraction CSV
def _write_rig(folder: Path) -> None:
    from livebridge.servo.rig import demo_rig

    demo_rig("simdynamixel://?ids=1-16&delay=0").save(folder / "head.toml")


CONTRACTION_CASES = _common_cases() + (
    Case("not utf-8", _bytes(b"t,jaw\n0,\xff\n"), ("not UTF-8",)),
    Case("empty file", _text(""), ("empty file", "line 1")),
    Case("header only", _text("t,jaw\n"), ("no rows",)),
    Case("no time column", _text("jaw,frontalis_L\n0.1,0.2\n"), ("no time column", "line 1")),
    Case("no muscle column", _text("t,frame\n0,1\n"), ("no muscle columns", "line 1")),
    Case("unknown muscle", _text("t,jaw,smile_L\n0,0.1,0.2\n"), ("'smile_L'", "--ignore-extra", "line 1")),
    Case("a column twice", _text("t,jaw,jaw\n0,0.1,0.2\n"), ("'jaw'", "repeats", "column 3")),
    Case("ragged row", _text("t,jaw\n0,0.1\n0.1,0.2,0.3\n0.2,0.1\n"), ("line 3", "3 fields")),
    Case("text in a cell", _text("t,jaw\n0,0.1\n0.1,wide\n"), ("line 3", "column 2 (jaw)", "'wide'")),
    Case("time not a number", _text("t,jaw\n0,0.1\nsoon,0.2\n"), ("line 3", "column 1 (t)")),
    Case("time missing", _text("t,jaw\n0,0.1\n,0.2\n"), ("line 3", "column 1 (t)", "finite time")),
    Case("time infinite", _text("t,jaw\n0,0.1\ninf,0.2\n"), ("line 3", "finite time")),
)


# ------------------------------------------------------------------------------------------------ landmark placing
LANDMARK_IDS_CASES = _toml_cases() + (
    Case("empty file", _text(""), ("no landmarks",)),
    Case("id a string", _text('chin = "12"\n'), ("chin", "vertex id")),
    Case("id fractional", _text("chin = 1.5\n"), ("chin", "vertex id")),
    Case("id negative", _text("nose_tip = 3\nchin = -1\n"), ("chin", ">= 0")),
    Case("id off the mesh", _text("nose_tip = 3\nchin = 999999\n"), ("chin", "vertex 999999", "does not exist")),
    Case("a table", _text("[chin]\nvertex = 3\n"), ("chin", "vertex id")),
    Case("22 required, 1 given", _text("chin = 3\n"), ("21 landmarks missing", "brow_outer_L")),
)
_ON_FACE = "chin,0,-80,89.94\n"
LANDMARK_POINTS_CASES = _common_cases() + (
    Case("not utf-8", _bytes(b"chin,0,\xff,1\n"), ("not UTF-8",)),
    Case("empty file", _text(""), ("no landmarks",)),
    Case("header only", _text("name,x,y,z\n"), ("no landmarks",)),
    Case("three fields", _text(_ON_FACE + "nose_tip,0,-7\n"), ("line 2", "4 fields")),
    Case("text coordinate", _text(_ON_FACE + "nose_tip,0,up,120\n"), ("line 2", "nose_tip", "numbers")),
    Case("NaN coordinate", _text(_ON_FACE + "nose_tip,0,nan,120\n"), ("line 2", "nose_tip", "finite")),
    Case("a landmark twice", _text(_ON_FACE + _ON_FACE), ("line 2", "'chin'", "twice")),
    Case("two landmarks at one point", _text(_ON_FACE + _ON_FACE.replace("chin", "nose_tip")),
         ("chin and nose_tip", "both at")),
    Case("far off the surface", _text(_ON_FACE + "nose_tip,0,-7,160\n"), ("nose_tip", "mm from the mesh surface")),
    Case("every point off the surface (in m)", _text("chin,0,-0.08,0.08994\nnose_tip,0,-0.007,0.1198\n"),
         ("2 points this far", "all of them", "units")),
)

_PICKED_CHIN = 'x="0" y="-80" z="89.94" name="chin" active="1"'


def _picked(*points: str, root: str = "PickedPoints") -> Callable[[Path], None]:
    """A MeshLab PickPoints file (as MeshLab writes it) of ``points``' attribute texts."""
    body = "".join(f" <point {attributes}/>\n" for attributes in points)
    return _text(f"<!DOCTYPE {root}>\n<{root}>\n <DocumentData>\n  <DataFileName name=\"builtin\"/>\n"
                 f" </DocumentData>\n{body}</{root}>\n")


PICKED_POINTS_CASES = _common_cases() + (
    Case("not xml", _text(_ON_FACE), ("PickPoints", "line 1")),
    Case("binary", _bytes(bytes(range(256))), ("PickPoints", "line 1")),
    Case("cut short", _text('<PickedPoints>\n <point x="0" y="1"'), ("PickPoints", "line 2")),
    Case("a template, not picked points", _picked('name="chin"', root="PickPointsTemplate"),
         ("<PickPointsTemplate>", "<PickedPoints>")),
    Case("no points", _picked(), ("no picked landmarks", "0 <point>")),
    Case("none picked", _picked('x="0" y="-80" z="89.94" name="chin" active="0"'), ("no picked landmarks",
                                                                                   "none of them active")),
    Case("a point without a name", _picked(_PICKED_CHIN, 'x="0" y="-7" z="120" active="1"'), ("point 2", "no name")),
    Case("no z", _picked(_PICKED_CHIN, 'x="0" y="-7" name="nose_tip"'), ("point 2", "nose_tip", "x=, y= and z=")),
    Case("text coordinate", _picked(_PICKED_CHIN, 'x="0" y="up" z="120" name="nose_tip"'),
         ("point 2", "nose_tip", "numbers")),
    Case("NaN coordinate", _picked(_PICKED_CHIN, 'x="0" y="nan" z="120" name="nose_tip"'),
         ("point 2", "nose_tip", "finite")),
    Case("a landmark twice", _picked(_PICKED_CHIN, _PICKED_CHIN), ("point 2", "'chin'", "twice")),
    Case("far off the surface", _picked(_PICKED_CHIN, 'x="0" y="-7" z="160" name="nose_tip" active="1"'),
         ("nose_tip", "mm from the mesh surface")),
)

# ------------------------------------------------------------------------------------------------ character folder
def _write_character_parts(folder: Path) -> None:
    """A character folder's images (the case writes its character.toml) and a contraction take."""
    import cv2

    (folder / "char").mkdir()
    cv2.imwrite(str(folder / "char" / "neutral.png"), np.full((40, 50, 3), 128, np.uint8))
    cv2.imwrite(str(folder / "char" / "s1.png"), np.full((10, 12, 3), 30, np.uint8))
    mask = np.zeros((40, 50), np.uint8)
    mask[5:30, 5:40] = 255
    cv2.imwrite(str(folder / "char" / "mask.png"), mask)
    cv2.imwrite(str(folder / "char" / "small_mask.png"), mask[:30])
    (folder / "take.csv").write_text("t,jaw\n0,0.5\n0.1,0.7\n")


def _character(region: str = "") -> Callable[[Path], None]:
    head = 'format = "livebridge-character"\nversion = 1\nneutral = "neutral.png"\n'
    body = region or ('[[regions]]\nname = "mouth"\nmuscles = ["jaw"]\nstates = [1]\nmask = "mask.png"\n'
                      '[[regions.samples]]\nmuscle = "jaw"\nstate = 1\nimage = "s1.png"\nat = [10, 10]\n')
    return _text(head + body)


def _jaw_region(states: str = "[1]", at: str = "[10, 10]", mask: str = "mask.png", muscle: str = "jaw",
                extra: str = "") -> str:
    return (f'[[regions]]\nname = "mouth"\nmuscles = ["{muscle}"]\nstates = {states}\nmask = "{mask}"\n{extra}'
            f'[[regions.samples]]\nmuscle = "{muscle}"\nstate = 1\nimage = "s1.png"\nat = {at}\n')


CHARACTER_CASES = _toml_cases() + (
    Case("not a character", _text('format = "livebridge-basis"\nversion = 1\n'), ("format", "not a character")),
    Case("a later version", _text('format = "livebridge-character"\nversion = 9\nneutral = "neutral.png"\n'),
         ("version", "9")),
    Case("no neutral image", _text('format = "livebridge-character"\nversion = 1\nneutral = "none.png"\n'
                                   'regions = []\n'), ("none.png", "file not found"), names_input=False),
    Case("no regions", _text('format = "livebridge-character"\nversion = 1\nneutral = "neutral.png"\n'),
         ("regions", "missing")),
    Case("a state without a sample", _character(_jaw_region(states="[2]")),
         ("regions[0].samples", "jaw state 2")),
    Case("a sample outside the canvas", _character(_jaw_region(at="[45, 10]")),
         ("s1.png", "jaw state 1", "outside the 50x40 canvas"), names_input=False),
    Case("a sample outside its mask", _character(_jaw_region(at="[38, 30]")),
         ("s1.png", "jaw state 1", "outside the region's mask"), names_input=False),
    Case("a mask of another size", _character(_jaw_region(mask="small_mask.png")),
         ("small_mask.png", "50x30", "50x40"), names_input=False),
    Case("a face mask without a warp", _character(_jaw_region(extra='mask_space = "face"\n')),
         ("mask_space", "[warp]")),
    Case("a muscle the take lacks", _character(_jaw_region(muscle="smile")), ("regions", "'smile'")),
    Case("placement not whole pixels", _character(_jaw_region(at="[10.5, 10]")), ("regions[0].samples[0].at",)),
)


# ------------------------------------------------------------------------------------------------ scans
_PLY = "ply\nformat {} 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n{}end_header\n"
_FACE_HEADER = "element face 1\nproperty list uchar int vertex_indices\n"


def _ply_binary(n_header: int, n_points: int, faces: bytes = b"", face_header: str = "") -> Callable[[Path], None]:
    points = np.arange(3 * n_points, dtype="<f4").tobytes()
    return _bytes(_PLY.format("binary_little_endian", n_header, face_header).encode() + points + faces)


PLY_CASES = _common_cases() + (
    Case("empty file", _text(""), ("empty file",)),
    Case("not a PLY", _text("hello\n"), ("not a PLY",)),
    Case("no end_header", _text("ply\nformat ascii 1.0\nelement vertex 1\n"), ("end_header",)),
    Case("unknown format", _text(_PLY.format("binary_middle_endian", 1, "") + "0 0 0\n"), ("header line 2",
                                                                                           "binary_middle_endian")),
    Case("unknown type", _text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n"),
         ("header line 4", "float128")),
    Case("no z", _text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                       "end_header\n0 0\n"), ("vertex", "no property z")),
    Case("ascii too few vertices", _text(_PLY.format("ascii", 3, "") + "0 0 0\n1 1 1\n"),
         ("vertex 2 of 3", "ends")),
    Case("ascii short row", _text(_PLY.format("ascii", 2, "") + "0 0 0\n1 1\n"), ("line 9", "vertex 1")),
    Case("ascii text", _text(_PLY.format("ascii", 1, "") + "0 up 0\n"), ("line 8", "vertex 0")),
    Case("ascii NaN", _text(_PLY.format("ascii", 2, "") + "0 0 0\n1 nan 1\n"), ("vertex 1", "not finite")),
    Case("binary truncated", _ply_binary(5, 4), ("vertex 4 of 5", "ends")),
    Case("binary rows past the count", _ply_binary(3, 5), ("24 bytes after the 3 vertex rows", "count")),
    Case("ascii rows past the count", _text(_PLY.format("ascii", 1, "") + "0 0 0\n1 1 1\n\n"),
         ("line 9", "1 more rows than the header promises")),
    Case("binary face past the end", _ply_binary(3, 3, b"\x03" + np.array([0, 1, 7], "<i4").tobytes(),
                                                 _FACE_HEADER), ("face", "vertex 7", "does not exist")),
    Case("binary face truncated", _ply_binary(3, 3, b"\x03\x00\x00", _FACE_HEADER), ("face 0 of 1", "ends")),
    Case("no vertices", _text(_PLY.format("ascii", 0, "")), ("no points",)),
    Case("binary list of -1 entries", _ply_binary(3, 3, b"\xff" + np.array([0, 1, 2], "<i4").tobytes(),
                                                  _FACE_HEADER.replace("uchar", "char")), ("face 0", "-1 entries")),
    Case("x a list", _text("ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\n"
                           "property float y\nproperty float z\nend_header\n1 0 0 0\n"), ("vertex", "x is a list")),
    Case("float colour above 1", _text(_PLY.format("ascii", 2, "property float red\nproperty float green\n"
                                                   "property float blue\n") + "0 0 0 0.5 0.5 0.5\n1 1 1 0.5 2 0\n"),
         ("point 1", "colour", "0-1")),
)
_TRIANGLE = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"
MESH_OBJ_CASES = _common_cases() + (
    Case("no vertices", _text("# nothing\n"), ("no vertices",)),
    Case("two coordinates a vertex", _text("v 0 0\nv 1 0\nv 0 1\nf 1 2 3\n"), ("line 1", "x y z")),
    Case("a vertex past any integer", _text(_TRIANGLE + "f 1 2 99999999999999999999999\n"),
         ("line 4", "vertex 99999999999999999999999")),
    Case("a vertex numbered 0", _text(_TRIANGLE + "f 0 1 2\n"), ("line 4", "from 1")),
    Case("a face of two corners", _text(_TRIANGLE + "f 1 2\n"), ("line 4", "3 or more")),
)


def _stl_binary(corners: np.ndarray, count: int | None = None, header: bytes = b"binary") -> Callable[[Path], None]:
    """A binary STL of triangles ``corners`` (m, 3, 3), its count field ``count`` (default m)."""
    records = np.zeros(len(corners), [("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
    records["corners"] = corners
    count = len(corners) if count is None else count
    return _bytes(header.ljust(80, b" ") + np.uint32(count).tobytes() + records.tobytes())


_STL_TRIANGLE = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], np.float32)
_STL_FACET = "facet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\n"
STL_CASES = _common_cases() + (
    Case("empty file", _text(""), ("empty file",)),
    Case("binary truncated", _stl_binary(np.repeat(_STL_TRIANGLE, 2, axis=0), count=3),
         ("binary STL of 3 triangles", "truncated")),
    Case("binary truncated, header 'solid'", _stl_binary(np.repeat(_STL_TRIANGLE, 2, axis=0), count=3,
                                                         header=b"solid \xff"), ("neither a binary STL",)),
    Case("binary NaN corner", _stl_binary(np.concatenate([_STL_TRIANGLE, _STL_TRIANGLE * np.nan])),
         ("triangle 1", "not finite")),
    Case("no triangles", _text("solid face\nendsolid face\n"), ("no triangles",)),
    Case("a facet of two corners", _text("solid f\n" + _STL_FACET.replace("vertex 0 1 0\n", "")),
         ("line 2", "2 corners")),
    Case("a corner not a number", _text("solid f\n" + _STL_FACET.replace("vertex 1 0 0", "vertex 1 zero 0")),
         ("line 5", "vertex x y z")),
    Case("a truncated facet", _text("solid f\n" + _STL_FACET.split("vertex 0 1 0")[0]), ("line 2", "endfacet")),
)
XYZ_CASES = _common_cases() + (
    Case("empty file", _text(""), ("empty file",)),
    Case("blank lines only", _text("\n  \n"), ("empty file",)),
    Case("header only", _text("x y z\n"), ("no points",)),
    Case("not utf-8", _bytes(b"1 2 3\n1 \xff 3\n"), ("not UTF-8",)),
    Case("two columns", _text("1 2 3\n4 5\n"), ("line 2", "at least 3 values")),
    Case("text", _text("1 2 3\n4 five 6\n"), ("line 2", "numbers")),
    Case("NaN", _text("1 2 3\n4 5 nan\n"), ("line 2", "finite")),
    Case("decimal commas", _text("1,5;2,5;3,5\n"), ("line 1", "decimal point")),
    Case("header with numbers after", _text("label 2 3\n"), ("line 1", "numbers")),
    Case("colour not a number", _text("x y z r g b\n1 2 3 0.5 0.5 0.5\n4 5 6 red 0 0\n"), ("line 3", "r, g, b")),
    Case("negative colour", _text("x y z r g b\n1 2 3 0.5 -0.5 0.5\n"), ("point 0", "colour")),
)
_SCANS = ("retarget", "scans", "--neutral-landmarks", "{dir}/lm.csv", "--expression", "jaw={dir}/jaw.ply")


def _write_scan_landmarks(folder: Path) -> None:
    (folder / "lm.csv").write_text("nose_tip,0,0,0\n")


def _scans(path: Path, folder: Path) -> list[str]:
    return [arg.format(dir=folder) for arg in _SCANS] + ["--neutral", str(path), "--out", str(folder / "b.npz")]


# ------------------------------------------------------------------------------------------------ phone takes
# A phone take (take/, as the recorder writes it) replayed by a phone session (replay.toml): a case spoils one
# of its files.
def _phone_take(folder: Path) -> None:
    from livebridge.simulators.iphone import SimulatedIPhone
    from livebridge.take.recorder import TakeRecorder

    phone = SimulatedIPhone(("jaw",))
    with TakeRecorder(folder / "take", ("jaw",), (), phone=True) as recorder:
        for k in range(3):
            recorder.record(phone.frame0 + k, 10.0 + k / 60, np.array([0.1 * k]), packet=phone.packet(phone.frame0 + k))
    (folder / "replay.toml").write_text('[source]\nkind = "livelinkface"\nurl = "replay://take?realtime=0"\n'
                                        "[outputs.render]\nenabled = false\n")


def _arkit_rows(change: Callable[[list[list[str]]], None]) -> Callable[[Path], None]:
    """The take's good ``arkit.csv`` (header + rows as fields) changed by ``change``."""
    def write(path: Path) -> None:
        rows = [line.split(",") for line in path.read_text().splitlines()]
        change(rows)
        path.write_text("".join(",".join(row) + "\n" for row in rows))
    return write


def _set(line: int, column: str, value: str) -> Callable[[list[list[str]]], None]:
    def change(rows: list[list[str]]) -> None:
        rows[line - 1][rows[0].index(column)] = value
    return change


def _manifest(change: Callable[[str], str]) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        path.write_text(change(path.read_text()))
    return write


PHONE_ARKIT_CASES = (
    Case("missing", lambda path: path.unlink(), ("file not found",)),
    Case("empty file", _text(""), ("empty file",)),
    Case("header only", _arkit_rows(lambda rows: rows.__delitem__(slice(1, None))), ("no packets",)),
    Case("not utf-8", _bytes(b"frame,seq\n\xff\n"), ("not UTF-8",)),
    Case("header renamed", _arkit_rows(_set(1, "jawOpen", "jaw_open")), ("line 1", "jawOpen", "jaw_open")),
    Case("a row short", _arkit_rows(lambda rows: rows[2].pop()), ("line 3", "fields")),
    Case("weight NaN", _arkit_rows(_set(2, "eyeBlinkLeft", "nan")), ("line 2", "eyeBlinkLeft", "weight")),
    Case("weight empty", _arkit_rows(_set(3, "jawOpen", "")), ("line 3", "jawOpen", "weight")),
    Case("weight above 1", _arkit_rows(_set(2, "mouthClose", "1.5")), ("line 2", "mouthClose", "[0, 1]")),
    Case("head turned past a quarter", _arkit_rows(_set(4, "headYaw", "-1.2")), ("line 4", "headYaw", "[-1, 1]")),
    Case("eye rotation text", _arkit_rows(_set(2, "rightEyeRoll", "up")), ("line 2", "rightEyeRoll", "'up'")),
    Case("sub-frame 1", _arkit_rows(_set(2, "sub_frame", "1")), ("line 2", "sub_frame", "[0, 1)")),
    Case("rate 0", _arkit_rows(_set(3, "rate_numerator", "0")), ("line 3", "rate_numerator", "positive")),
    Case("frame number fractional", _arkit_rows(_set(2, "frame_number", "12.5")), ("line 2", "frame_number",
                                                                                  "integer")),
    Case("time infinite", _arkit_rows(_set(2, "t", "inf")), ("line 2", "column 3 (t)")),
)
PHONE_MANIFEST_CASES = (
    Case("a camera take", _manifest(lambda text: "\n".join(line for line in text.splitlines() if not line.startswith(
        ("source", "arkit", "device_id", "subject"))).replace("version = 2", "version = 1") + "\n"),
         ("arkit", "recorded from cameras")),
    Case("version 1 with a phone", _manifest(lambda text: text.replace("version = 2", "version = 1")),
         ("source", "version 1")),
    Case("a newer version", _manifest(lambda text: text.replace("version = 2", "version = 3")),
         ("version", "newer livebridge")),
    Case("source unknown", _manifest(lambda text: text.replace('source = "livelinkface"', 'source = "android"')),
         ("source", "android")),
    Case("phone without arkit", _manifest(lambda text: text.replace('arkit = "arkit.csv"\n', "")), ("arkit",
                                                                                                   "missing")),
    Case("arkit outside the take", _manifest(lambda text: text.replace('"arkit.csv"', '"../arkit.csv"')),
         ("arkit", "file name inside the take")),
    Case("device id a number", _manifest(lambda text: re.sub(r'(?m)^device_id = ".*"$', "device_id = 5", text)),
         ("device_id", "text")),
)


# ------------------------------------------------------------------------------------------------ markerless
def _markerless_take(folder: Path) -> None:
    (folder / "frames").mkdir()
    import cv2

    cv2.imwrite(str(folder / "frames" / "0000.png"), np.zeros((24, 36), np.uint8))


def _markerless_npz(**arrays) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        with path.open("wb") as stream:
            np.savez(stream, **arrays)
    return write


MARKERLESS_MODEL_CASES = _common_cases() + (
    Case("not a zip", _text("model\n"), ("not a markerless model",)),
    Case("a bare array", _npy, ("not a markerless model", "single array")),
    Case("no manifest", _markerless_npz(a=np.zeros(3)), ("manifest", "not a markerless model")),
    Case("manifest not JSON", _markerless_npz(manifest=np.array("{")), ("manifest", "not JSON")),
    Case("another format", _markerless_npz(manifest=np.array('{"format": "livebridge-basis"}')),
         ("manifest.format", "livebridge-markerless")),
    Case("no regions", _markerless_npz(manifest=np.array(json.dumps(
        {"format": "livebridge-markerless", "version": 1, "muscle_names": ["jaw"], "regions": [], "gestures": [],
         "normalisation": {}, "method": "ica"}))), ("manifest.regions", "no regions")),
)
GESTURE_LIST_CASES = _toml_cases() + (
    Case("no gestures", _text("x = 1\n"), ("gesture", "[[gesture]]")),
    Case("unnamed gesture", _text("[[gesture]]\nmuscles = { jaw = 1.0 }\n"), ("gesture[0].name",)),
    Case("unknown muscle", _text("[[gesture]]\nname = 'g'\nmuscles = { smile = 1.0 }\n"),
         ("gesture[0].muscles.smile", "unknown muscle")),
    Case("level out of range", _text("[[gesture]]\nname = 'g'\nmuscles = { jaw = 1.5 }\n"),
         ("gesture[0].muscles.jaw", "(0, 1]")),
    Case("names repeat", _text("[[gesture]]\nname = 'g'\nmuscles = { jaw = 1.0 }\n[[gesture]]\nname = 'g'\n"
                               "muscles = { jaw = 0.5 }\n"), ("repeat",)),
)


FORMATS = (
    Format("basis", "basis.npz", lambda path, folder: ["basis", "show", str(path), "--out", str(folder / "out.png")],
           BASIS_CASES),
    Format("markers", "markers.toml", lambda path, folder: ["basis", "show", str(folder / "basis.npz"), "--markers",
                                                            str(path), "--out", str(folder / "out.png")],
           MARKER_CASES, setup=_write_basis),
    Format("calibration", "calibration.toml", lambda path, folder: ["calibrate", "show", str(path)],
           CALIBRATION_CASES),
    Format("session", "session.toml", lambda path, folder: ["run", str(path)], SESSION_CASES),
    Format("landmark ids", "ids.toml", lambda path, folder: ["landmarks", "place", "builtin", "--vertices", str(path),
                                                            "--require-22", "--out", str(folder / "lm.toml")],
           LANDMARK_IDS_CASES),
    Format("landmark points", "points.csv", lambda path, folder: ["landmarks", "place", "builtin", "--points",
                                                                 str(path), "--out", str(folder / "lm.toml")],
           LANDMARK_POINTS_CASES),
    Format("picked points", "points.pp", lambda path, folder: ["landmarks", "place", "builtin", "--points",
                                                               str(path), "--out", str(folder / "lm.toml")],
           PICKED_POINTS_CASES),
    Format("landmarks", "landmarks.toml", lambda path, folder: ["landmarks", "show", str(folder / "basis.npz"),
                                                               str(path), "--out", str(folder / "out.png")],
           MARKER_CASES, setup=_write_basis),
    Format("contractions", "contractions.csv",
           lambda path, folder: ["play", str(path), "--rig", str(folder / "head.toml"), "--no-render"],
           CONTRACTION_CASES, setup=_write_rig),
    Format("character", "char/character.toml",
           lambda path, folder: ["character", "render", str(folder / "take.csv"), "--character",
                                 str(folder / "char"), "--out", str(folder / "frames"), "--no-progress"],
           CHARACTER_CASES, setup=_write_character_parts),
    Format("landmark mesh", "mesh.obj", lambda path, folder: ["landmarks", "place", str(path), "--points",
                                                             str(folder / "points.csv"), "--out",
                                                             str(folder / "lm.toml")],
           MESH_OBJ_CASES, setup=lambda folder: (folder / "points.csv").write_text("chin,0,0,0\n")),
    Format("scan ply", "neutral.ply", _scans, PLY_CASES, setup=_write_scan_landmarks),
    Format("scan stl", "neutral.stl", _scans, STL_CASES, setup=_write_scan_landmarks),
    Format("landmark mesh stl", "mesh.stl", lambda path, folder: ["retarget", "basis", "--source", "builtin",
                                                                 "--source-landmarks", "builtin-22", "--target",
                                                                 str(path), "--target-landmarks", "builtin-22",
                                                                 "--out", str(folder / "out.npz")], STL_CASES),
    Format("scan xyz", "neutral.xyz", _scans, XYZ_CASES, setup=_write_scan_landmarks),
    Format("phone take arkit", "take/arkit.csv", lambda path, folder: ["run", str(folder / "replay.toml")],
           PHONE_ARKIT_CASES, setup=_phone_take),
    Format("phone take manifest", "take/take.toml", lambda path, folder: ["run", str(folder / "replay.toml")],
           PHONE_MANIFEST_CASES, setup=_phone_take),
    Format("markerless model", "model.npz", lambda path, folder: ["markerless", "analyse", str(folder / "frames"),
                                                                  "--model", str(path)],
           MARKERLESS_MODEL_CASES, setup=_markerless_take),
    Format("gesture list", "gestures.toml", lambda path, folder: ["markerless", "train", str(folder / "frames"),
                                                                  "--gestures", str(path), "--out",
                                                                  str(folder / "model.npz")],
           GESTURE_LIST_CASES, setup=_markerless_take),
)
CASES = [pytest.param(fmt, case, id=f"{fmt.name}: {case.name}") for fmt in FORMATS for case in fmt.cases]


def _snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every file (its bytes) and folder (None) under ``folder``."""
    return {str(p.relative_to(folder)): None if p.is_dir() else p.read_bytes() for p in sorted(folder.rglob("*"))
            if not p.is_symlink() and (p.is_dir() or os.access(p, os.R_OK))}


@pytest.fixture
def crash_dir(tmp_path, monkeypatch):
    folder = tmp_path / "crash-reports"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    return folder


def _refused(result, words, crash_dir: Path, work: Path, before, threads: set) -> str:
    """Assert what every refusal shows: exit != 0, one ``Error:`` line holding ``words``, no traceback, no
    crash report, ``work`` unchanged, no thread left running of those started since ``threads`` (the ones
    alive before); returns the error line."""
    output = result.output
    errors = [line for line in output.splitlines() if line.startswith("Error:")]
    assert result.exit_code != 0, output
    assert isinstance(result.exception, SystemExit), repr(result.exception)  # nothing escaped the boundary
    assert "Traceback" not in output and "Aborted" not in output, output
    assert len(errors) == 1, output
    for word in words:
        assert word in errors[0], (word, errors[0])
    assert not list(crash_dir.iterdir()), "reported as a bug: " + errors[0]
    assert _snapshot(work) == before
    left = _left_running(threads)
    assert not left, f"a refusal left threads running: {left}"
    return errors[0]


@pytest.mark.parametrize("fmt,case", CASES)
def test_malformed_input_is_one_error_line(tmp_path, crash_dir, fmt, case):
    work = tmp_path / "work"
    work.mkdir()
    fmt.setup(work)
    path = work / fmt.filename
    held = case.write(path)
    threads = set(threading.enumerate())
    try:
        before = _snapshot(work)
        result = CliRunner().invoke(main, fmt.command(path, work))
    finally:
        if held is not None:
            held.close()
    _refused(result, (fmt.filename,) * case.names_input + case.expect, crash_dir, work, before, threads)


LIBRARY_THREADS = ("tqdm_monitor",)
"""Threads a library keeps for the process (started once, on first use), not by the refused command."""


def _left_running(before: set, wait_s: float = 1.0) -> list[str]:
    """The names of threads started since ``before`` that are still alive after up to ``wait_s``."""
    deadline = time.monotonic() + wait_s
    while True:
        left = [t.name for t in threading.enumerate() if t not in before and t.name not in LIBRARY_THREADS]
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.05)


# ================================================================================================ command options
# Every option that takes a number, port, path or URL, malformed: each case adds its arguments to the command's
# valid ``base`` ones ("{dir}" is the work folder, "{port}" a port another socket holds), and the one error line
# must name the option and what is wrong. Nothing may run: every refusal comes before any work.

@dataclass(frozen=True)
class Bad:
    """Malformed arguments, added to the command's base ones (a repeated option's last value wins), or the
    whole command line (``whole``: a malformed positional argument)."""

    name: str
    args: tuple[str, ...]
    expect: tuple[str, ...]
    whole: bool = False


@dataclass(frozen=True)
class Command:
    """A command line, its valid arguments, and its table of malformed ones."""

    name: str
    base: tuple[str, ...]
    cases: tuple[Bad, ...]


def _numbers(option: str, values: tuple[str, ...], *base: str) -> tuple[Bad, ...]:
    """One case per malformed value of a numeric ``option``; the error names the option and the value."""
    return tuple(Bad(f"{option} {value}", (*base, option, value), (option, value)) for value in values)


_NOT_FINITE = ("nan", "inf", "-inf", "abc", "")
_BAD_COUNT = ("-1", "1.5", "x", "99999999999999999999")
_BAD_PORT = ("-1", "65536", "99999", "http")
_MISSING = "{dir}/no/such/folder"


def _output_cases(option: str = "--out", suffix: str = ".png") -> tuple[Bad, ...]:
    """An output file in a missing folder, that is a folder, or that exists (kept without --force)."""
    return (
        Bad(f"{option} in a missing folder", (option, f"{_MISSING}/x{suffix}"), (option, "does not exist")),
        Bad(f"{option} a folder", (option, "{dir}"), (option, "is a folder")),
        Bad(f"{option} exists", (option, f"{{dir}}/existing{suffix}"), (option, "already exists", "--force")),
    )


def _input_cases(option: str) -> tuple[Bad, ...]:
    return (Bad(f"{option} missing", (option, "{dir}/nothing.toml"), (option, "nothing.toml", "file not found")),
            Bad(f"{option} a folder", (option, "{dir}"), (option, "is a directory")))


def _held_port() -> tuple[object, int]:
    import socket

    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    return busy, busy.getsockname()[1]


_DEMO = ("demo", "--frames", "1", "--no-servo", "--unpaced", "--size", "160x100", "--port", "0")
_RIG = ("--cameras", "{dir}/calibration.toml")
_CONVERT = ("take", "convert", "{dir}/take.npz", "{dir}/out.csv")
_CHARACTER_RENDER = ("character", "render", "{dir}/contractions.csv", "--character", "builtin", "--out",
                     "{dir}/out.mp4")
_RETARGET = ("--source", "builtin", "--source-landmarks", "builtin-22", "--target", "builtin", "--target-landmarks",
             "builtin-22")
_QUALITY = ("--basis", "{dir}/basis.npz", "--markers", "{dir}/markers.toml", "--take", "{dir}/take.npz")

COMMANDS = (
    Command("run", ("run", "{dir}/session.toml"), (
        *_numbers("--frames", _BAD_COUNT),
        Bad("SESSION missing", ("run", "{dir}/nothing.toml"), ("SESSION", "nothing.toml", "file not found"), True),
    )),
    Command("demo", _DEMO, (
        *_numbers("--frames", _BAD_COUNT + ("1000000001",)),
        *_numbers("--cameras", ("1", "9", "-2", "x")),
        *_numbers("--seed", ("-1", "4294967296", "x")),
        *_numbers("--fps", _NOT_FINITE + ("0", "-5", "0.5", "1e9")),
        *_numbers("--size", ("0x0", "-5x10", "100000x100000", "640", "axb", "10x10", "")),
        *_numbers("--port", _BAD_PORT),
        Bad("--port in use", ("--port", "{port}"), ("--port", "127.0.0.1:{port}", "address already in use")),
        Bad("--host not local", ("--host", "0.0.0.0"), ("--host", "0.0.0.0", "--allow-remote")),
        Bad("--host a LAN address", ("--host", "192.168.1.1"), ("--host", "--allow-remote")),
        Bad("--host empty", ("--host", " "), ("--host",)),
        Bad("--host not on this machine", ("--host", "203.0.113.7", "--allow-remote"),
            ("--host", "203.0.113.7", "address not available")),
        *_numbers("--vmc", ("127.0.0.1:99999", "127.0.0.1:0", "127.0.0.1", ":39539", "0.0.0.0:39539",
                            "255.255.255.255:1", "127.0.0.1:-1")),
        Bad("--record in a missing folder", ("--record", f"{_MISSING}/take"), ("--record", "does not exist")),
        Bad("--record exists", ("--record", "{dir}"), ("--record", "already exists")),
        Bad("--record-frames without --record", ("--record-frames",), ("--record-frames", "--record")),
        Bad("--source unknown", ("--source", "iphone"), ("--source", "iphone")),
        Bad("--source livelinkface with a rig option", ("--source", "livelinkface"), ("--size", "simulated rig")),
    )),
    Command("node", ("node", "--cameras", "sim://rig?cameras=1&size=160x100"), (
        Bad("--host not tcp", ("--host", "udp://127.0.0.1:7000"), ("--host", "tcp://HOST:PORT")),
        Bad("--host without a port", ("--host", "tcp://127.0.0.1"), ("--host", "tcp://HOST:PORT")),
        *_numbers("--host", ("tcp://127.0.0.1:65535", "tcp://127.0.0.1:-1", "tcp://127.0.0.1:x")),
        Bad("--host not local", ("--host", "tcp://0.0.0.0:7000"), ("--host", "--allow-remote")),
        Bad("--host port in use", ("--host", "tcp://127.0.0.1:{port}"), ("--host", "cannot serve", "in use")),
        *_input_cases("--key"),
        Bad("--key too short", ("--key", "{dir}/short.key"), ("short.key", "at least 32 bytes")),
        Bad("--cameras unknown scheme", ("--cameras", "webcam://0"), ("--cameras", "webcam")),
        Bad("--cameras sharing an id", ("--cameras", "sim://rig?cameras=1&size=160x100"),
            ("--cameras", "share an id")),
    )),
    Command("basis import", ("basis", "import", "{dir}/manifest.toml", "--out", "{dir}/new.npz"), (
        *_output_cases(suffix=".npz"),
        Bad("--shapes missing", ("--shapes", "{dir}/nothing"), ("--shapes", "nothing", "file not found")),
    )),
    Command("basis show", ("basis", "show", "{dir}/basis.npz", "--out", "{dir}/new.png"), (
        *_output_cases(),
        *_numbers("--yaw", _NOT_FINITE + ("1e9",)),
        *_numbers("--dpi", ("0", "-5", "100000", "nan")),
        *_numbers("--panel-size", _NOT_FINITE + ("0", "-1", "1e6")),
        Bad("--crop-y nan", ("--crop-y", "0", "nan"), ("--crop-y", "nan")),
        Bad("--crop-y upside down", ("--crop-y", "5", "1"), ("--crop-y", "below")),
        Bad("--crop-y infinite", ("--crop-y", "-inf", "1"), ("--crop-y", "-inf")),
        Bad("--markers missing", ("--markers", "{dir}/nothing.toml"), ("--markers", "nothing.toml", "not found")),
        Bad("--muscle unknown", ("--muscle", "nose"), ("--muscle", "'nose'")),
        Bad("BASIS missing", ("basis", "show", "{dir}/nothing.npz", "--out", "{dir}/new.png"),
            ("BASIS", "nothing.npz", "file not found"), True),
    )),
    Command("basis check", ("basis", "check", *_QUALITY), (
        *_input_cases("--basis"), *_input_cases("--markers"), *_input_cases("--take"),
        Bad("--out-dir a file", ("--out-dir", "{dir}/basis.npz"), ("--out-dir", "is a file")),
        Bad("--out-dir in a missing folder", ("--out-dir", f"{_MISSING}/out"), ("--out-dir", "does not exist")),
        Bad("--out-dir holds the summary", ("--out-dir", "{dir}/checked"), ("--out-dir", "already exists", "--force")),
    )),
    Command("basis refine", ("basis", "refine", *_QUALITY, "--out", "{dir}/new.npz"), (
        *_output_cases(suffix=".npz"),
        *_input_cases("--basis"),
        *_numbers("--max-iterations", ("0", "-1", "1000000000", "x")),
        *_numbers("--tolerance", _NOT_FINITE + ("-0.1", "2")),
    )),
    Command("markers design", ("markers", "design", "--out", "{dir}/new.toml"), (
        *_output_cases(suffix=".toml"),
        *_numbers("--count", ("0", "1000000000") + _BAD_COUNT),
        *_numbers("--min-spacing", _NOT_FINITE + ("-1", "1e9")),
        *_numbers("--head", ("-1", "1000000", "x")),
        *_numbers("--min-observers", ("0", "1000000")),
        *_numbers("--min-views", ("0", "-3", "1000"), *_RIG),
        *_numbers("--max-view-deg", _NOT_FINITE + ("0", "91"), *_RIG),
        *_numbers("--view-margin", _NOT_FINITE + ("-1", "1e9"), *_RIG),
        *_input_cases("--cameras"),
        Bad("--basis missing", ("--basis", "{dir}/nothing.npz"), ("--basis", "nothing.npz", "file not found")),
    )),
    Command("markers report", ("markers", "report", "{dir}/markers.toml", "--basis", "{dir}/basis.npz"), (
        *_input_cases("--cameras"),
        *_numbers("--min-views", ("0",), *_RIG),
        *_numbers("--max-view-deg", ("nan", "inf"), *_RIG),
        Bad("LAYOUT_FILE missing", ("markers", "report", "{dir}/nothing.toml"),
            ("LAYOUT_FILE", "nothing.toml", "file not found"), True),
    )),
    Command("solve", ("solve", "{dir}/take.npz", "--markers", "{dir}/markers.toml", "--out", "{dir}/c.csv"), (
        *_output_cases(suffix=".csv"),
        *_output_cases("--take", ".npz"),
        *_output_cases("--markers-out", ".toml"),
        Bad("--out's .png exists", ("--out", "{dir}/existing"), ("--out", "existing.png", "--force")),
        *_numbers("--neutral-frame", ("-1", "1.5", "x", "", "autox")),
        Bad("--units unknown", ("--units", "inch"), ("--units", "inch")),
        Bad("--mode unknown", ("--mode", "fast"), ("--mode", "fast")),
        Bad("--markers missing", ("--markers", "{dir}/nothing.toml"), ("--markers", "nothing.toml", "not found")),
        Bad("--correspond without a vertex", ("--markers", "auto", "--correspond", "M1"), ("--correspond", "'M1'")),
        Bad("--correspond a negative vertex", ("--markers", "auto", "--correspond", "M1=-3"),
            ("--correspond", "'M1=-3'")),
        Bad("--correspond without auto", ("--correspond", "M1=3"), ("--correspond", "only with --markers auto")),
        *_input_cases("--basis"),
        Bad("FILE missing", ("solve", "{dir}/nothing.c3d", "--markers", "auto", "--out", "{dir}/c.csv"),
            ("MARKER_FILE", "nothing.c3d", "file not found"), True),
    )),
    Command("process", ("process", "{dir}/checked", "--out", "{dir}/results", "--workers", "0"), (
        Bad("--out missing", ("--out", _MISSING), ("--out", "folder not found")),
        Bad("--out a file", ("--out", "{dir}/basis.npz"), ("--out", "is a file")),
        Bad("--stage unknown", ("--stage", "all"), ("--stage", "all")),
        Bad("--mode unknown", ("--mode", "fast"), ("--mode", "fast")),
        *_numbers("--workers", ("-1", "x", "1.5", "2000")),
        Bad("--scheduler and --workers", ("--scheduler", "tcp://127.0.0.1:8786"), ("--workers", "not both")),
        *(Bad(f"--scheduler {address}", ("process", "{dir}/checked", "--out", "{dir}/results", "--scheduler",
                                        address), ("--scheduler", address), True)
          for address in ("http://127.0.0.1:8786", "tcp://127.0.0.1", "tcp://:8786", "tcp://127.0.0.1:0",
                          "tcp://127.0.0.1:99999", "127.0.0.1:8786")),
        Bad("--calibration with --stage solve", ("--calibration", "{dir}/calibration.toml"),
            ("--calibration", "only with")),
        Bad("--markers missing", ("--markers", "{dir}/nothing.toml"), ("--markers", "nothing.toml", "not found")),
        *_input_cases("--basis"),
        Bad("TAKES missing", ("process", "{dir}/nothing", "--out", "{dir}/results"),
            ("TAKES", "nothing", "folder not found"), True),
        Bad("TAKES given twice", ("process", "{dir}/checked", "{dir}/checked", "--out", "{dir}/results"),
            ("checked", "given twice"), True),
        Bad("results exist", ("process", "{dir}/checked", "--out", "{dir}", "--workers", "0"),
            ("checked", "already exists", "--force"), True),
    )),
    Command("markers place", ("markers", "place", "{dir}/take.npz", "--out", "{dir}/new.toml"), (
        *_output_cases(suffix=".toml"),
        *_numbers("--neutral-frame", ("-1", "2.5", "first")),
        Bad("--units unknown", ("--units", "ft"), ("--units", "ft")),
        Bad("--correspond without a name", ("--correspond", "=12"), ("--correspond", "'=12'")),
        *_input_cases("--basis"),
        Bad("FILE a folder", ("markers", "place", "{dir}/checked", "--out", "{dir}/new.toml"),
            ("MARKER_FILE", "checked", "is a directory"), True),
    )),
    Command("calibrate board", ("calibrate", "board", "charuco:5x4:30:22:DICT_4X4_50", "--out", "{dir}/new.png"), (
        *_output_cases(),
        *_numbers("--dpi", ("0", "-5", "71", "100000", "nan", "3e2")),
        Bad("SPEC malformed", ("calibrate", "board", "chessboard:7", "--out", "{dir}/new.png"),
            ("SPEC", "chessboard:7"), True),
        Bad("SPEC of 500x500 squares", ("calibrate", "board", "charuco:500x500:100:80:DICT_4X4_50", "--out",
                                        "{dir}/new.png"), ("SPEC", "at most 100 squares"), True),
        Bad("SPEC too big to print", ("calibrate", "board", "chessboard:30x21:100", "--out",
                                      "{dir}/new.png"), ("SPEC", "does not print"), True),
    )),
    Command("calibrate run", ("calibrate", "run", "--board", "chessboard:7x5:25", "--videos", "a={dir}/basis.npz",
                              "--videos", "b={dir}/markers.toml", "--out", "{dir}/new.toml"), (
        *_output_cases(suffix=".toml"),
        *_numbers("--every", ("0", "-1", "1000000000", "x")),
        *_numbers("--frames", ("0", "-1", "1000000000")),
        *_numbers("--origin-view", ("-1", "x")),
        Bad("--board malformed", ("--board", "charuco:7x5"), ("--board", "charuco:7x5")),
        Bad("--videos missing", ("--videos", "c={dir}/nothing.mp4"), ("--videos", "nothing.mp4", "not found")),
        Bad("--videos without a name", ("--videos", "{dir}/basis.npz"), ("--videos", "NAME=FILE")),
        Bad("--videos a name twice", ("--videos", "a={dir}/session.toml"), ("--videos", "'a'", "twice")),
        Bad("--report in a missing folder", ("--report", f"{_MISSING}/report"), ("--report", "does not exist")),
        Bad("--report a file", ("--report", "{dir}/basis.npz"), ("--report", "already exists")),
    )),
    Command("calibrate run --sources", ("calibrate", "run", "--board", "chessboard:7x5:25", "--out",
                                        "{dir}/new.toml"), (
        Bad("no scheme", ("--sources", "a=webcam0"), ("--sources", "scheme")),
        Bad("unknown scheme", ("--sources", "a=webcam://0"), ("--sources", "unknown camera URL scheme")),
        Bad("a parameter twice", ("--sources", "a=sim://rig?fps=30&fps=60"), ("--sources", "'fps'", "2 times")),
        Bad("sim board spec malformed", ("--sources", "a=sim://rig?board=chessboard:7x7&camera=0"),
            ("board", "3 ':'-separated")),
        Bad("sim board camera out of range", ("--sources", "a=sim://rig?board=chessboard:7x7:40&camera=5"),
            ("camera", "0..1")),
        Bad("sim board unknown parameter", ("--sources", "a=sim://rig?board=chessboard:7x7:40&fps=30"),
            ("fps", "unknown")),
        Bad("sim board size", ("--sources", "a=sim://rig?board=chessboard:7x7:40&size=10x10"), ("size", "640x480")),
        Bad("sim face unknown parameter", ("--sources", "a=sim://face?cameras=2"), ("cameras", "unknown")),
        Bad("sim face size", ("--sources", "a=sim://face?size=10x10"), ("size", "32..4096")),
        Bad("sim face head rig", ("--sources", "a=sim://face?head_rig=helmet"), ("head_rig", "leds, none")),
    )),
    Command("calibrate show", ("calibrate", "show", "{dir}/calibration.toml"), (
        Bad("PATH missing", ("calibrate", "show", "{dir}/nothing.toml"), ("PATH", "nothing.toml", "file not found"),
            True),
    )),
    Command("sim dynamixel", ("sim", "dynamixel"), (
        Bad("--ids a billion", ("--ids", "1-999999999"), ("--ids", "1-999999999", "0..252")),
        Bad("--ids downwards", ("--ids", "5-1"), ("--ids", "5-1")),
        Bad("--ids text", ("--ids", "one"), ("--ids", "'one'")),
        Bad("--ids twice", ("--ids", "1-3,2"), ("--ids", "twice")),
        *_numbers("--baud", ("7", "-1", "x")),
        *_numbers("--corrupt", _NOT_FINITE + ("-0.1", "1.5")),
        *_numbers("--drop", ("nan", "2")),
        *_numbers("--seed", ("-1", "4294967296")),
        *_numbers("--delay", ("-1", "255", "1e3")),
    )),
    Command("sim maestro", ("sim", "maestro"), (
        *_numbers("--channels", ("0", "25", "1000000000", "-1")),
        *_numbers("--device", ("-1", "128")),
        *_numbers("--corrupt", ("nan", "inf", "-1")),
        *_numbers("--drop", ("1.01",)),
        *_numbers("--seed", ("-1",)),
    )),
    Command("sim ssc32", ("sim", "ssc32"), (
        *_numbers("--corrupt", ("nan", "1.5")),
        *_numbers("--drop", ("-0.1", "inf")),
        *_numbers("--seed", ("x", "-1")),
    )),
    Command("servo scan", ("servo", "scan"), (
        Bad("URL ids a billion", ("simdynamixel://?ids=1-999999999",), ("simdynamixel://?ids=1-999999999", "ids",
                                                                       "0..252")),
        Bad("--ids a billion", ("simdynamixel://", "--ids", "1-999999999"), ("--ids", "1-999999999")),
        *[Bad(f"URL {url}", (url,), (url, parameter)) for url, parameter in (
            ("simmaestro://?channels=999999999", "channels"), ("simmaestro://?device=128", "device"),
            ("simssc32://?channels=0", "channels"), ("simssc32://?drop=nan", "drop"),
            ("simdynamixel://?corrupt=inf", "corrupt"), ("simdynamixel://?delay=-1", "delay"),
            ("simdynamixel://?seed=-1", "seed"))],
        Bad("URL without scheme", ("ttyUSB0",), ("ttyUSB0", "scheme")),
        Bad("URL unknown scheme", ("usb://x",), ("usb://x", "unknown bus URL scheme")),
    )),
    Command("play", ("play", "{dir}/contractions.csv", "--rig", "{dir}/head.toml"), (
        *_numbers("--speed", _NOT_FINITE + ("0", "-1", "101")),
        *_numbers("--port", _BAD_PORT, "--render"),
        *_input_cases("--rig"),
        Bad("--basis missing", ("--basis", "{dir}/nothing.npz"), ("--basis", "nothing.npz", "file not found")),
        Bad("CONTRACTIONS missing", ("play", "{dir}/nothing.csv", "--rig", "{dir}/head.toml"),
            ("CONTRACTIONS", "nothing.csv"), True),
        Bad("--rig left out", ("play", "{dir}/contractions.csv"), ("--rig",), True),
    )),
    Command("bench", ("bench",), (
        Bad("NAME unknown", ("fastest",), ("NAME", "'fastest'")),
    )),
    Command("retarget scans", ("retarget", "scans", "--neutral", "{dir}/contractions.csv", "--neutral-landmarks",
                               "{dir}/contractions.csv", "--expression", "jaw={dir}/contractions.csv", "--out",
                               "{dir}/b.npz"), (
        *_output_cases(suffix=".npz"),
        *_output_cases("--grid-obj", ".toml"),
        *_input_cases("--neutral"),
        *_input_cases("--neutral-landmarks"),
        *_input_cases("--reference"),
        *_numbers("--crop-radius", _NOT_FINITE + ("0", "-1")),
        *_numbers("--workers", ("0", "-1", "1.5", "x", "257")),
        Bad("--grid-obj where --out writes", ("--grid-obj", "{dir}/b.npz"), ("--grid-obj", "--out writes there")),
        Bad("--grid not WxH", ("--grid", "150"), ("--grid", "WxH")),
        Bad("--grid too small", ("--grid", "1x150"), ("--grid",)),
        Bad("--expression without =", ("--expression", "jaw"), ("--expression", "NAME=SCAN[:LM]")),
        Bad("--expression twice", ("--expression", "jaw=a.ply"), ("--expression", "'jaw'", "twice")),
        Bad("--normalise unknown", ("--normalise", "warp"), ("--normalise", "warp")),
        Bad("--units unknown", ("--units", "inch"), ("--units", "inch")),
    )),
    Command("landmarks place", ("landmarks", "place", "builtin", "--vertices", "{dir}/ids.toml", "--out",
                                "{dir}/lm.toml"), (
        *_output_cases(suffix=".toml"),
        *_input_cases("--vertices"),
        *_input_cases("--points"),
        *_numbers("--max-distance", _NOT_FINITE + ("0", "-1")),
        Bad("--units unknown", ("--units", "inch"), ("--units", "inch")),
        Bad("both --vertices and --points", ("--points", "{dir}/contractions.csv"), ("--vertices", "--points")),
        Bad("MESH missing", ("landmarks", "place", "{dir}/nothing.obj", "--vertices", "{dir}/ids.toml", "--out",
                             "{dir}/lm.toml"), ("MESH", "nothing.obj", "file not found"), True),
        Bad("MESH of an unknown type", ("landmarks", "place", "{dir}/contractions.csv", "--vertices",
                                        "{dir}/ids.toml", "--out", "{dir}/lm.toml"),
            ("contractions.csv", "unknown mesh type", "'.csv'"), True),
    )),
    Command("landmarks show", ("landmarks", "show", "builtin", "builtin-22", "--out", "{dir}/lm.png"), (
        *_output_cases(),
        *_numbers("--yaw", _NOT_FINITE + ("91", "-91")),
        *_numbers("--dpi", ("0", "601", "x")),
        Bad("--out not an image", ("landmarks", "show", "builtin", "builtin-22", "--out", "{dir}/lm.xyz"),
            ("--out", "lm.xyz", "an image is written as"), True),
        Bad("LANDMARKS missing", ("landmarks", "show", "builtin", "{dir}/nothing.toml", "--out", "{dir}/lm.png"),
            ("LANDMARKS", "nothing.toml", "file not found"), True),
        Bad("LANDMARKS not on this mesh", ("landmarks", "show", "{dir}/basis.npz", "builtin-22", "--out",
                                           "{dir}/lm.png"), ("builtin-22", "made for a mesh of 17672 triangles"),
            True),
    )),
    *[Command(f"retarget {verb}", ("retarget", verb, *_RETARGET, *extra), (
        Bad("a landmark missing on the target", ("--target-landmarks", "{dir}/lm21.toml"),
            ("lm21.toml", "nose_tip", "missing")),
        Bad("a non-manifold target", ("--target", "{dir}/fan.obj"), ("fan.obj", "non-manifold")),
        Bad("an unwelded target", ("--target", "{dir}/soup.obj"), ("soup.obj", "unwelded")),
        Bad("a target facing inwards", ("--target", "{dir}/flipped.obj"), ("flipped.obj", "face into the head")),
        Bad("a target wound every which way", ("--target", "{dir}/mixed.obj"), ("mixed.obj", "every which way")),
        Bad("a landmark off the surface", ("--target", "{dir}/collapsed.obj"),
            ("builtin-22", "nose_tip", "off the surface")),
        Bad("a hole at a landmark", ("--target", "{dir}/holed.obj"), ("builtin-22", "nose_tip", "hole")),
        Bad("--source-landmarks missing", ("--source-landmarks", "{dir}/nothing.toml"),
            ("--source-landmarks", "nothing.toml", "file not found")),
    )) for verb, extra in (("basis", ("--out", "{dir}/target.npz")),
                           ("au", ("--au", "12", "--out", "{dir}/au.obj")))],
    Command("retarget au options", ("retarget", "au", *_RETARGET, "--au", "12", "--out", "{dir}/au.obj"), (
        *_numbers("--magnitude", _NOT_FINITE + ("1.5", "-0.1")),
        Bad("--au unknown", ("--au", "99"), ("au99", "no control points")),
        Bad("--au twice", ("--au", "au12"), ("--au", "au12", "more than once")),
        Bad("--side unknown", ("--side", "up"), ("--side", "up")),
        Bad("--expression missing", ("--expression", "{dir}/nothing.obj"),
            ("--expression", "nothing.obj", "file not found")),
        Bad("--expression non-manifold", ("--expression", "{dir}/fan.obj"), ("fan.obj", "non-manifold")),
        Bad("--expression-landmarks missing a landmark", ("--expression", "builtin", "--expression-landmarks",
                                                          "{dir}/lm21.toml"), ("lm21.toml", "nose_tip", "missing")),
        Bad("a source mesh with no --expression", ("--source", "{dir}/flipped.obj"),
            ("flipped.obj", "--expression", "no muscles")),
    )),
    Command("take show", ("take", "show", "{dir}/take.npz"), (
        *_numbers("--rate", _NOT_FINITE + ("0", "-1", "1e9")),
        Bad("--units unknown", ("--units", "inch"), ("--units", "inch")),
        Bad("FILE missing", ("take", "show", "{dir}/nothing.csv"), ("FILE", "nothing.csv", "file not found"), True),
        Bad("FILE a folder", ("take", "show", "{dir}"), ("FILE", "is a directory"), True),
    )),
    Command("take convert", _CONVERT, (
        *_numbers("--rate", ("nan", "0", "-inf")),
        Bad("--units unknown", ("--units", "km"), ("--units", "km")),
        Bad("OUT exists", (*_CONVERT[:3], "{dir}/existing.png"), ("OUT", "existing.png", "--force"), True),
        Bad("OUT in a missing folder", (*_CONVERT[:3], f"{_MISSING}/x.c3d"), ("OUT", "does not exist"), True),
        Bad("OUT a folder", (*_CONVERT[:3], "{dir}"), ("OUT", "is a folder"), True),
        Bad("OUT of an unknown type", (*_CONVERT[:3], "{dir}/out.xyz"), ("OUT", "'.xyz'", ".trc"), True),
        Bad("IN missing", ("take", "convert", "{dir}/nothing.trc", "{dir}/out.csv"), ("IN", "nothing.trc",
                                                                                    "file not found"), True),
    )),
    Command("character render", _CHARACTER_RENDER, (
        *_numbers("--fps", _NOT_FINITE + ("0", "-5", "1001")),
        *_output_cases(),
        Bad("--character missing", ("--character", "{dir}/nothing"), ("--character", "folder not found")),
        Bad("--character a file", ("--character", "{dir}/session.toml"), ("--character", "not a folder")),
        Bad("--basis missing", ("--basis", "{dir}/nothing.npz"), ("--basis", "file not found")),
        Bad("TAKE missing", ("character", "render", "{dir}/nothing.csv", "--character", "builtin", "--out",
                             "{dir}/out.mp4"), ("TAKE", "nothing.csv", "not found"), True),
    )),
    Command("character from-training", ("character", "from-training", "{dir}/take.npz", "--out", "{dir}/char"), (
        *_numbers("--feather", _NOT_FINITE + ("-1", "101")),
        Bad("--out exists", ("--out", "{dir}/checked"), ("--out", "already exists")),
        Bad("--out in a missing folder", ("--out", f"{_MISSING}/char"), ("--out", "does not exist")),
        Bad("MODEL missing", ("character", "from-training", "{dir}/nothing.npz", "--out", "{dir}/char"),
            ("MODEL", "nothing.npz", "file not found"), True),
    )),
    Command("character template", ("character", "template", "{dir}/take.npz", "--out", "{dir}/sheets"), (
        Bad("--out exists", ("--out", "{dir}/checked"), ("--out", "already exists")),
        Bad("--out in a missing folder", ("--out", f"{_MISSING}/sheets"), ("--out", "does not exist")),
    )),
)
OPTION_CASES = [pytest.param(command, case, id=f"{command.name}: {case.name}")
                for command in COMMANDS for case in command.cases]


def _option_work(folder: Path) -> None:
    """The files the commands' valid arguments name, and outputs that already exist."""
    _npz()(folder / "basis.npz")
    _markers()(folder / "markers.toml")
    _calibration()(folder / "calibration.toml")
    (folder / "session.toml").write_text(_SIM)
    (folder / "contractions.csv").write_text("t,jaw\n0,0.5\n")
    (folder / "ids.toml").write_text("chin = 3\n")
    _write_rig(folder)
    (folder / "manifest.toml").write_text("x = 1\n")
    (folder / "short.key").write_bytes(b"too short")
    (folder / "take.npz").write_bytes(b"not read: the options are refused first")
    for name in ("existing.png", "existing.npz", "existing.toml"):
        (folder / name).write_bytes(b"keep me")
    (folder / "checked").mkdir()
    (folder / "results").mkdir()
    (folder / "checked" / "take.basis-check.txt").write_text("keep me")
    _retarget_work(folder)


def _retarget_work(folder: Path) -> None:
    """Landmarks without nose_tip; the built-in face as OBJ made non-manifold, and with nose_tip's triangle
    collapsed (the landmark off any surface); same triangle counts, so the shipped landmarks fit them."""
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.landmarks import load_landmark_set

    landmarks = load_landmark_set("builtin-22")
    landmarks.subset(np.array([n != "nose_tip" for n in landmarks.names])).save(folder / "lm21.toml")
    basis = builtin_basis()
    fan = basis.triangles.copy()
    a, b = fan[0, :2]
    fan[-2:] = [[a, b, fan[100, 2]], [a, b, fan[200, 2]]]  # edge (a, b) in four triangles
    collapsed = basis.triangles.copy()
    vertex = collapsed[landmarks.triangles[landmarks.names.index("nose_tip")], 0]
    collapsed[landmarks.triangles[landmarks.names.index("nose_tip")]] = [vertex, vertex, vertex]
    holed = basis.triangles.copy()  # the triangles around nose_tip's collapsed onto one far vertex: a hole
    own = landmarks.triangles[landmarks.names.index("nose_tip")]
    around = np.flatnonzero(np.isin(holed, holed[own]).any(axis=1))
    holed[around[around != own]] = holed[0, 0]
    flipped = basis.triangles[:, ::-1]
    mixed = basis.triangles.copy()
    mixed[::2] = mixed[::2, ::-1]
    for name, triangles in (("fan.obj", fan), ("collapsed.obj", collapsed), ("holed.obj", holed),
                            ("flipped.obj", flipped), ("mixed.obj", mixed)):
        lines = [f"v {x} {y} {z}" for x, y, z in basis.neutral] + [f"f {i + 1} {j + 1} {k + 1}"
                                                                   for i, j, k in triangles]
        (folder / name).write_text("\n".join(lines) + "\n")
    corners = basis.neutral[basis.triangles].reshape(-1, 3)  # every triangle its own three vertices, as in STL
    lines = [f"v {x} {y} {z}" for x, y, z in corners] + [f"f {3 * t + 1} {3 * t + 2} {3 * t + 3}"
                                                         for t in range(len(basis.triangles))]
    (folder / "soup.obj").write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def option_work(tmp_path_factory) -> Path:
    """:func:`_option_work` made once; each case runs in its own copy, since a case may not leave it as it was."""
    folder = tmp_path_factory.mktemp("option_work")
    _option_work(folder)
    return folder


@pytest.mark.parametrize("command,case", OPTION_CASES)
def test_a_malformed_option_is_one_error_line(tmp_path, crash_dir, option_work, command, case):
    work = tmp_path / "work"
    shutil.copytree(option_work, work)
    held, port = _held_port() if any("{port}" in arg for arg in case.args) else (None, 0)
    fill = {"dir": str(work), "port": str(port)}
    threads = set(threading.enumerate())
    try:
        before = _snapshot(work)
        args = [arg.format(**fill) for arg in (case.args if case.whole else (*command.base, *case.args))]
        result = CliRunner().invoke(main, args)
    finally:
        if held is not None:
            held.close()
    _refused(result, tuple(word.format(**fill) for word in case.expect), crash_dir, work, before, threads)


def test_the_option_corpus_runs_hundreds_of_cases():
    """The number the issue asks to quote (with the file cases above)."""
    assert len(OPTION_CASES) >= 200 and len(CASES) >= 150

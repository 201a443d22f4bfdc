"""A bad-input corpus for every take format and every ``livebridge take`` option, generated here (no stored files).

Each case starts from a good input written by the real writers (TakeRecorder, Take.save, RawFrameWriter), damages
it one way, and runs the real command line on it (click's CliRunner on ``livebridge.cli.main``):

- take directories (``take.toml``, ``markers.csv``) and every option through ``livebridge take export-c3d``;
- ``.npz`` takes through ``livebridge basis check --take``;
- raw-frame timestamp files and image folders through ``livebridge run`` on a session replaying them;
- marker files of other systems (C3D, TRC, CSV) through ``livebridge take show``.

Every case asserts: exit code != 0 through click's own exit (no escaped exception), a message naming the file and
the field, line/column or option, no ``Traceback``, and every input file unchanged (hashed before and after; no
file left behind either). ``contractions.csv``, which no command reads alone, is checked through
:func:`load_take_dir` the same way.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from factories import random_basis

from livebridge.capture.frame import Frame
from livebridge.cli import main
from livebridge.errors import InputError
from livebridge.face.markers import MarkerSet
from livebridge.take.directory import load_take_dir
from livebridge.take.npz import Take
from livebridge.take.raw_frames import RawFrameWriter
from livebridge.take.recorder import TakeRecorder

MUSCLES = ("m0", "m1")
MARKERS = ("a", "b")
N_FRAMES = 8


@dataclass(frozen=True)
class Case:
    """One malformed input: ``damage`` changes the good input in ``folder``; ``args`` the command line (``{dir}``
    is the case folder); every string of ``expect`` must appear in the output."""

    id: str
    damage: Callable[[Path], None]
    args: tuple[str, ...]
    expect: tuple[str, ...]


def _hashes(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` by relative path."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _run(case: Case, folder: Path):
    case.damage(folder)
    before = _hashes(folder)
    args = [a.replace("{dir}", str(folder)) for a in case.args]
    result = CliRunner().invoke(main, args)
    output = result.output
    assert result.exit_code != 0, output
    assert isinstance(result.exception, SystemExit), f"escaped: {result.exception!r}"  # click's clean exit
    assert "Traceback" not in output
    for piece in case.expect:
        assert piece.replace("{dir}", str(folder)) in output, output
    assert _hashes(folder) == before, "an input file changed or a file was left behind"
    return output


# -- inputs ----------------------------------------------------------------------------------------------------

def _values(k: int):
    markers = np.array([[k, 2.0 * k, 3.0], [np.nan, np.nan, np.nan] if k % 3 == 0 else [1.0, k, -k]])
    return np.array([0.1 * k, 0.2]), markers, markers * 0.5, (0.1, 0.2)


@pytest.fixture(scope="module")
def good_take(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("good") / "take"
    with TakeRecorder(path, MUSCLES, MARKERS, fps=60) as recorder:
        for k in range(N_FRAMES):
            recorder.record(k, 1.0 + k / 60, *_values(k))
    return path


@pytest.fixture(scope="module")
def good_npz(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("npz")
    basis = random_basis(np.random.default_rng(2))
    basis.save(folder / "basis.npz")
    MarkerSet(MARKERS, np.array([0, 1]), np.full((2, 3), 1 / 3), ("upper", "lower"), ("face", "face")).save(
        folder / "markers.toml")
    rng = np.random.default_rng(3)
    Take(np.arange(N_FRAMES) / 30, MARKERS, displacements=rng.normal(size=(N_FRAMES, 2, 3)),
         contractions=rng.random((N_FRAMES, 2)), muscle_names=MUSCLES, fps=30.0).save(folder / "take.npz")
    return folder


@pytest.fixture(scope="module")
def good_frames(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("frames")
    with RawFrameWriter(folder / "frames", ".pgm") as writer:
        for name in ("cam0", "cam1"):
            for k in range(4):
                writer.write(Frame(np.full((24, 32), 9 * k, np.uint8), 1.0 + k / 30, k, name, 1000.0, 1.0, "sync"))
    (folder / "session.toml").write_text('[cameras]\nurls = ["replay://frames?realtime=0"]\n'
                                         '[outputs.render]\nenabled = false\n')
    return folder


def _copy(good: Path, tmp_path: Path) -> Path:
    folder = tmp_path / "case"
    shutil.copytree(good, folder)
    return folder


# -- damage ----------------------------------------------------------------------------------------------------

def _write(name: str, data: str | bytes) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        target = folder / name
        if isinstance(data, bytes):
            target.write_bytes(data)
        else:
            target.write_text(data)
    return damage


def _edit(name: str, old: str, new: str, count: int = 1) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        text = (folder / name).read_text()
        assert old in text, (name, old, text)
        (folder / name).write_text(text.replace(old, new, count))
    return damage


def _line(name: str, number: int, new: str) -> Callable[[Path], None]:
    """Replace line ``number`` (1-based) of a text file."""
    def damage(folder: Path) -> None:
        lines = (folder / name).read_text().split("\n")
        lines[number - 1] = new
        (folder / name).write_text("\n".join(lines))
    return damage


def _remove(name: str) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        target = folder / name
        shutil.rmtree(target) if target.is_dir() else target.unlink()
    return damage


def _make_dir(name: str) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        _remove(name)(folder)
        (folder / name).mkdir()
    return damage


def _truncate(name: str, keep: float = 0.5) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[: int(len(data) * keep)])
    return damage


def _c3d_byte(offset, value: int) -> Callable[[Path], None]:
    """Set one byte of good.c3d: at ``offset``, or where ``offset(data)`` says."""
    def damage(folder: Path) -> None:
        data = bytearray((folder / "good.c3d").read_bytes())
        data[offset(data) if callable(offset) else offset] = value
        (folder / "good.c3d").write_bytes(bytes(data))
    return damage


def _processor_byte(data: bytearray) -> int:
    """Where a C3D file's processor type is: the 4th byte of its parameter section (header byte 0: its block)."""
    return (data[0] - 1) * 512 + 3


def _nothing(folder: Path) -> None:
    pass


def _both(*damages: Callable[[Path], None]) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        for one in damages:
            one(folder)
    return damage


# -- take directories and `livebridge take export-c3d` -----------------------------------------------------------

_EXPORT = ("take", "export-c3d", "{dir}")
_EXPORT_NEW = (*_EXPORT, "--out", "{dir}/new.c3d")  # the closed take's own markers.c3d exists
_TOML = "take.toml"
_CSV = "markers.csv"
_TAKE_DIR_CASES = [
    Case("take-dir-missing", _nothing, ("take", "export-c3d", "{dir}/nope"), ("nope", "does not exist")),
    Case("take-dir-is-a-file", _nothing, ("take", "export-c3d", "{dir}/markers.csv"), ("markers.csv", "directory")),
    Case("take-dir-without-manifest", _remove(_TOML), _EXPORT_NEW, ("not a take directory", "take.toml")),
    Case("manifest-is-a-folder", _make_dir(_TOML), _EXPORT_NEW, ("not a take directory", "take.toml")),
    Case("manifest-not-toml", _write(_TOML, "format = [unclosed\n"), _EXPORT_NEW, ("take.toml", "not valid TOML")),
    Case("manifest-not-utf8", _write(_TOML, b'format = "\xff\xfe"\n'), _EXPORT_NEW, ("take.toml", "UTF-8")),
    Case("manifest-empty", _write(_TOML, ""), _EXPORT_NEW, ("take.toml", "format", "missing")),
    Case("manifest-unknown-key", _edit(_TOML, "fps =", "fsp ="), _EXPORT_NEW, ("take.toml", "fsp", "unknown key")),
    Case("manifest-missing-markers", _edit(_TOML, 'marker_names = [\n    "a",\n    "b",\n]\n', ""), _EXPORT_NEW,
         ("take.toml", "marker_names", "missing")),
    Case("manifest-markers-a-string", _edit(_TOML, 'marker_names = [\n    "a",\n    "b",\n]',
                                            'marker_names = "a,b"'), _EXPORT_NEW, ("take.toml", "marker_names")),
    Case("manifest-markers-numbers", _edit(_TOML, '"a",', "1,"), _EXPORT_NEW, ("take.toml", "marker_names")),
    Case("manifest-markers-twice", _edit(_TOML, '"b",', '"a",'), _EXPORT_NEW,
         ("take.toml", "marker_names", "distinct")),
    Case("manifest-fps-nan", _edit(_TOML, "fps = 60.0", "fps = nan"), _EXPORT_NEW, ("take.toml", "fps", "finite")),
    Case("manifest-fps-negative", _edit(_TOML, "fps = 60.0", "fps = -1"), _EXPORT_NEW, ("take.toml", "fps")),
    Case("manifest-fps-a-string", _edit(_TOML, "fps = 60.0", 'fps = "60"'), _EXPORT_NEW, ("take.toml", "fps")),
    Case("manifest-fps-huge", _edit(_TOML, "fps = 60.0", "fps = 1e300"), _EXPORT_NEW, ("take.toml", "fps", "Hz")),
    Case("manifest-version-newer", _edit(_TOML, "version = 1", "version = 99"), _EXPORT_NEW, ("take.toml", "version")),
    Case("manifest-version-a-string", _edit(_TOML, "version = 1", 'version = "1"'), _EXPORT_NEW,
         ("take.toml", "version")),
    Case("manifest-wrong-format", _edit(_TOML, '"livebridge-take-dir"', '"other"'), _EXPORT_NEW,
         ("take.toml", "format")),
    Case("manifest-calibration-outside", _edit(_TOML, "fps =", 'calibration = "../../etc/passwd"\nfps ='), _EXPORT_NEW,
         ("take.toml", "calibration", "inside the take")),
    Case("manifest-frames-negative", _edit(_TOML, "frames = 8", "frames = -1"), _EXPORT_NEW, ("take.toml", "frames")),
    Case("manifest-frames-written-text", _edit(_TOML, "fps =", 'frames_written = "lots"\nfps ='), _EXPORT_NEW,
         ("take.toml", "frames_written")),
    Case("markers-missing", _remove(_CSV), _EXPORT_NEW, ("markers.csv", "file not found")),
    Case("markers-is-a-folder", _make_dir(_CSV), _EXPORT_NEW, ("markers.csv", "cannot read")),
    Case("markers-empty", _write(_CSV, ""), _EXPORT_NEW, ("markers.csv", "empty")),
    Case("markers-header-only", _write(_CSV, "frame,seq,t,a_x,a_y,a_z,b_x,b_y,b_z\n"), _EXPORT_NEW,
         ("markers.csv", "no frames")),
    Case("markers-not-utf8", _write(_CSV, b"frame,seq,t,a_x,a_y,a_z,b_x,b_y,b_z\n0,0,1.0,\xff,0,0,,,\n"), _EXPORT_NEW,
         ("markers.csv", "UTF-8")),
    Case("markers-binary", _write(_CSV, b"\x89PNG\r\n\x1a\n\xff\xfe\x00\x00"), _EXPORT_NEW, ("markers.csv", "UTF-8")),
    Case("markers-header-renamed", _line(_CSV, 1, "frame,seq,t,a_x,a_y,a_z,c_x,b_y,b_z"), _EXPORT_NEW,
         ("markers.csv", "line 1", "c_x")),
    Case("markers-header-short", _line(_CSV, 1, "frame,seq,t,a_x,a_y,a_z"), _EXPORT_NEW, ("markers.csv", "line 1")),
    Case("markers-ragged-short", _line(_CSV, 4, "2,2,1.03,1,2"), _EXPORT_NEW, ("markers.csv", "line 4", "fields")),
    Case("markers-ragged-long", _line(_CSV, 5, "3,3,1.05,1,2,3,4,5,6,7,8"), _EXPORT_NEW, ("markers.csv", "line 5")),
    Case("markers-not-a-number", _line(_CSV, 3, "1,1,1.0167,1.0,two,3.0,1.0,1.0,-1.0"), _EXPORT_NEW,
         ("markers.csv", "line 3, column 5 (a_y)", "two")),
    Case("markers-infinite", _line(_CSV, 3, "1,1,1.0167,1.0,inf,3.0,1.0,1.0,-1.0"), _EXPORT_NEW,
         ("markers.csv", "line 3, column 5 (a_y)")),
    Case("markers-nan-text", _line(_CSV, 3, "1,1,1.0167,nan,1,3.0,1.0,1.0,-1.0"), _EXPORT_NEW,
         ("markers.csv", "line 3, column 4 (a_x)")),
    Case("markers-empty-time", _line(_CSV, 3, "1,1,,1.0,2.0,3.0,1.0,1.0,-1.0"), _EXPORT_NEW,
         ("markers.csv", "line 3, column 3 (t)")),
    Case("markers-semicolons", _line(_CSV, 2, "0;0;1.0;0;0;3;;;"), _EXPORT_NEW, ("markers.csv", "line 2")),
    Case("one-frame-no-rate", _both(_edit(_TOML, "fps = 60.0\n", ""),
                                    _write(_CSV, "frame,seq,t,a_x,a_y,a_z,b_x,b_y,b_z\n0,0,1.0,1,2,3,,,\n")),
         _EXPORT_NEW, ("take.toml", "fps", "frame rate")),
]

_OPTION_CASES = [
    *[Case(f"rate-{value}", _nothing, (*_EXPORT_NEW, "--rate", value), ("--rate", value))
      for value in ("nan", "inf", "-inf", "0", "-1", "1e9", "abc", "", "0x10")],
    Case("out-folder-missing", _nothing, (*_EXPORT, "--out", "{dir}/no/such/folder/x.c3d"),
         ("{dir}/no/such/folder", "does not exist")),
    Case("out-exists-default", _nothing, _EXPORT, ("markers.c3d", "exists", "--force")),
    Case("out-exists-elsewhere", _write("other.c3d", b"keep me"), (*_EXPORT, "--out", "{dir}/other.c3d"),
         ("other.c3d", "exists", "--force")),
    Case("out-is-a-folder", _nothing, (*_EXPORT, "--out", "{dir}"), ("--out", "directory")),
    Case("out-is-the-markers-csv", _nothing, (*_EXPORT, "--out", "{dir}/markers.csv", "--force"),
         ("markers.csv", "the take's own records")),
    Case("out-is-the-manifest", _nothing, (*_EXPORT, "--out", "{dir}/take.toml", "--force"),
         ("take.toml", "the take's own records")),
    Case("unknown-option", _nothing, (*_EXPORT, "--fps", "30"), ("--fps",)),
]


@pytest.mark.parametrize("case", _TAKE_DIR_CASES + _OPTION_CASES, ids=lambda c: c.id)
def test_a_bad_take_directory_or_export_option_is_refused(case, good_take, tmp_path):
    _run(case, _copy(good_take, tmp_path))


def test_the_good_take_exports(good_take, tmp_path):
    folder = _copy(good_take, tmp_path)
    result = CliRunner().invoke(main, [*_EXPORT[:2], str(folder), "--out", str(folder / "new.c3d"), "--rate", "30"])
    assert result.exit_code == 0, result.output
    again = CliRunner().invoke(main, [*_EXPORT[:2], str(folder), "--force"])
    assert again.exit_code == 0, again.output
    assert sorted(p.name for p in folder.iterdir() if p.suffix in (".c3d", ".partial")) == ["markers.c3d", "new.c3d"]


def test_a_failed_export_leaves_no_partial_file_and_the_old_file_intact(good_take, tmp_path, monkeypatch):
    import errno

    import livebridge.atomic

    def disk_full(descriptor):  # the half-written file reaches the disk, and the disk is full
        raise OSError(errno.ENOSPC, "No space left on device")

    folder = _copy(good_take, tmp_path)
    monkeypatch.setattr(livebridge.atomic.os, "fsync", disk_full)
    output = _run(Case("disk-full", _nothing, (*_EXPORT, "--force"), ("markers.c3d", "No space left")), folder)
    assert "cannot write" in output


# -- .npz takes through `livebridge basis check --take` ----------------------------------------------------------

def _npz(**changes) -> Callable[[Path], None]:
    """Rewrite take.npz with arrays replaced (None: removed) and the manifest's keys changed (``manifest``
    itself: the raw manifest array)."""
    def damage(folder: Path) -> None:
        with np.load(folder / "take.npz") as data:
            arrays = {key: data[key] for key in data.files}
        manifest = json.loads(str(arrays["manifest"]))
        for key, value in changes.items():
            if key.startswith("m_"):
                manifest.pop(key[2:]) if value is None else manifest.__setitem__(key[2:], value)
            elif value is None:
                arrays.pop(key)
            else:
                arrays[key] = value
        if "manifest" not in changes:
            arrays["manifest"] = np.array(json.dumps(manifest))
        arrays = {key: value for key, value in arrays.items() if value is not None}
        np.savez_compressed(folder / "take.npz", **arrays)
    return damage


def _flip_bytes(name: str) -> Callable[[Path], None]:
    """Corrupt the compressed data of the first member (the zip directory stays readable)."""
    def damage(folder: Path) -> None:
        data = bytearray((folder / name).read_bytes())
        with zipfile.ZipFile(folder / name) as archive:
            info = archive.infolist()[0]
        start = info.header_offset + 30 + len(info.filename) + 10
        for k in range(start, start + 20):
            data[k] ^= 0xFF
        (folder / name).write_bytes(bytes(data))
    return damage


def _save_array(name: str, array) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        with open(folder / name, "wb") as stream:
            np.save(stream, array)
    return damage


_CHECK = ("basis", "check", "--basis", "{dir}/basis.npz", "--markers", "{dir}/markers.toml", "--take",
          "{dir}/take.npz")
_T = np.arange(N_FRAMES) / 30
_NPZ_CASES = [
    Case("npz-missing", _remove("take.npz"), _CHECK, ("take.npz", "not found")),
    Case("npz-is-a-folder", _make_dir("take.npz"), _CHECK, ("take.npz", "directory")),
    Case("npz-empty", _write("take.npz", b""), _CHECK, ("take.npz", "not a livebridge take")),
    Case("npz-truncated", _truncate("take.npz"), _CHECK, ("take.npz", "truncated")),
    Case("npz-truncated-to-header", _truncate("take.npz", 0.02), _CHECK, ("take.npz", "not a livebridge take")),
    Case("npz-text", _write("take.npz", "t,a_x\n0,1\n"), _CHECK, ("take.npz", "not a livebridge take")),
    Case("npz-single-npy", _save_array("take.npz", np.zeros((3, 3))), _CHECK, ("take.npz", ".npy")),
    Case("npz-corrupt-member", _flip_bytes("take.npz"), _CHECK, ("take.npz", "damaged")),
    Case("npz-object-array", _npz(t=np.array([1, "x", None], dtype=object)), _CHECK,
         ("take.npz", "t", "cannot read")),
    Case("npz-no-t", _npz(t=None), _CHECK, ("take.npz", "missing array", "t")),
    Case("npz-no-manifest", _npz(manifest=None), _CHECK, ("take.npz", "manifest")),
    Case("npz-unknown-array", _npz(extra=np.zeros(3)), _CHECK, ("take.npz", "extra", "unknown")),
    Case("npz-no-data", _npz(displacements=None), _CHECK, ("take.npz", "displacements or positions")),
    Case("npz-manifest-not-json", _npz(manifest=np.array("{not json")), _CHECK, ("take.npz", "manifest", "JSON")),
    Case("npz-manifest-a-list", _npz(manifest=np.array("[1, 2]")), _CHECK, ("take.npz", "manifest", "object")),
    Case("npz-manifest-numbers", _npz(manifest=np.arange(3.0)), _CHECK, ("take.npz", "manifest", "JSON string")),
    Case("npz-manifest-bytes", _npz(manifest=np.array(b"{}")), _CHECK, ("take.npz", "manifest")),
    Case("npz-format", _npz(m_format="other"), _CHECK, ("take.npz", "manifest.format")),
    Case("npz-version-newer", _npz(m_version=7), _CHECK, ("take.npz", "manifest.version", "newer")),
    Case("npz-version-text", _npz(m_version="1"), _CHECK, ("take.npz", "manifest.version")),
    Case("npz-version-missing", _npz(m_version=None), _CHECK, ("take.npz", "manifest.version")),
    Case("npz-unknown-key", _npz(m_fsp=30), _CHECK, ("take.npz", "manifest.fsp", "unknown")),
    Case("npz-markers-missing", _npz(m_marker_names=None), _CHECK, ("take.npz", "manifest.marker_names")),
    Case("npz-markers-empty", _npz(m_marker_names=[]), _CHECK, ("take.npz", "manifest.marker_names")),
    Case("npz-markers-numbers", _npz(m_marker_names=[1, 2]), _CHECK, ("take.npz", "manifest.marker_names")),
    Case("npz-markers-a-string", _npz(m_marker_names="ab"), _CHECK, ("take.npz", "manifest.marker_names")),
    Case("npz-markers-twice", _npz(m_marker_names=["a", "a"]), _CHECK, ("take.npz", "manifest.marker_names")),
    Case("npz-markers-too-many", _npz(m_marker_names=["a", "b", "c"]), _CHECK, ("take.npz", "displacements")),
    Case("npz-muscles-a-number", _npz(m_muscle_names=3), _CHECK, ("take.npz", "manifest.muscle_names")),
    Case("npz-fps-nan", _npz(m_fps=float("nan")), _CHECK, ("take.npz", "manifest.fps")),
    Case("npz-fps-negative", _npz(m_fps=-30), _CHECK, ("take.npz", "manifest.fps")),
    Case("npz-fps-text", _npz(m_fps="30"), _CHECK, ("take.npz", "manifest.fps")),
    Case("npz-t-text", _npz(t=np.array(["0.0"] * N_FRAMES)), _CHECK, ("take.npz", "t", "numbers")),
    Case("npz-t-complex", _npz(t=_T + 1j), _CHECK, ("take.npz", "t", "numbers")),
    Case("npz-t-2d", _npz(t=_T[:, None]), _CHECK, ("take.npz", "t", "dimensions")),
    Case("npz-t-empty", _npz(t=np.zeros(0), displacements=np.zeros((0, 2, 3)), contractions=None), _CHECK,
         ("take.npz", "t", "no frames")),
    Case("npz-t-backwards", _npz(t=_T[::-1].copy()), _CHECK, ("take.npz", "t", "non-decreasing")),
    Case("npz-t-nan", _npz(t=np.where(_T > 0.1, np.nan, _T)), _CHECK, ("take.npz", "t", "finite")),
    Case("npz-t-too-short", _npz(t=_T[:3]), _CHECK, ("take.npz", "displacements", "shape")),
    Case("npz-displacements-bool", _npz(displacements=np.ones((N_FRAMES, 2, 3), bool)), _CHECK,
         ("take.npz", "displacements", "numbers")),
    Case("npz-displacements-2d", _npz(displacements=np.zeros((N_FRAMES, 6))), _CHECK,
         ("take.npz", "displacements", "dimensions")),
    Case("npz-displacements-xy", _npz(displacements=np.zeros((N_FRAMES, 2, 2))), _CHECK,
         ("take.npz", "displacements", "shape")),
    Case("npz-displacements-inf", _npz(displacements=np.full((N_FRAMES, 2, 3), np.inf)), _CHECK,
         ("take.npz", "displacements", "infinite")),
    Case("npz-contractions-shape", _npz(contractions=np.zeros((N_FRAMES, 3))), _CHECK,
         ("take.npz", "contractions", "shape")),
    Case("npz-contractions-1d", _npz(contractions=np.zeros(N_FRAMES)), _CHECK,
         ("take.npz", "contractions", "dimensions")),
    Case("npz-head-pose-shape", _npz(head2world=np.zeros((N_FRAMES, 3, 4))), _CHECK,
         ("take.npz", "head2world", "shape")),
]


@pytest.mark.parametrize("case", _NPZ_CASES, ids=lambda c: c.id)
def test_a_bad_npz_take_is_refused(case, good_npz, tmp_path):
    _run(case, _copy(good_npz, tmp_path))


def test_the_good_npz_take_loads(good_npz):
    take = Take.load(good_npz / "take.npz")
    assert take.marker_names == MARKERS and take.muscle_names == MUSCLES and take.fps == 30.0


# -- raw frames through `livebridge run` (replay://) -------------------------------------------------------------

_RUN = ("run", "{dir}/session.toml", "--frames", "1")
_STAMPS = "frames/cam0.csv"
_RAW_CASES = [
    Case("stamps-not-a-number", _line(_STAMPS, 3, "1,zero,1000.0,1.0,sync,cam0"), _RUN,
         ("cam0.csv", "line 3, column 2 (t_capture)", "zero")),
    Case("stamps-seq-float", _line(_STAMPS, 3, "1.5,1.03,1000.0,1.0,sync,cam0"), _RUN,
         ("cam0.csv", "line 3, column 1 (seq)")),
    Case("stamps-time-inf", _line(_STAMPS, 3, "1,inf,1000.0,1.0,sync,cam0"), _RUN,
         ("cam0.csv", "line 3, column 2 (t_capture)")),
    Case("stamps-gain-inf", _line(_STAMPS, 3, "1,1.03,1000.0,-inf,sync,cam0"), _RUN,
         ("cam0.csv", "line 3, column 4 (gain)")),
    Case("stamps-ragged-short", _line(_STAMPS, 3, "1,1.03"), _RUN, ("cam0.csv", "line 3", "fields")),
    Case("stamps-ragged-long", _line(_STAMPS, 4, "2,1.06,1000.0,1.0,sync,cam0,extra"), _RUN,
         ("cam0.csv", "line 4", "fields")),
    Case("stamps-unknown-column", _line(_STAMPS, 1, "seq,t_capture,exposure_us,gain,sync_domian,source_id"), _RUN,
         ("cam0.csv", "line 1", "sync_domian")),
    Case("stamps-missing-column", _write(_STAMPS, "seq\n0\n1\n"), _RUN, ("cam0.csv", "t_capture", "missing")),
    Case("stamps-empty", _write(_STAMPS, ""), _RUN, ("cam0.csv", "missing")),
    Case("stamps-not-utf8", _write(_STAMPS, b"seq,t_capture\n0,\xff\xfe\n"), _RUN, ("cam0.csv", "UTF-8")),
    Case("stamps-a-folder", _make_dir(_STAMPS), _RUN, ("cam0.csv", "cannot read")),
    Case("images-none", _both(*[_remove(f"frames/cam1/{k:06d}.pgm") for k in range(4)]), _RUN,
         ("cam1", "no images")),
    Case("camera-missing", _write("session.toml", '[cameras]\nurls = ["replay://frames?cameras=cam7"]\n'
                                  '[outputs.render]\nenabled = false\n'), _RUN, ("cam7", "no images or video")),
]


@pytest.mark.parametrize("case", _RAW_CASES, ids=lambda c: c.id)
def test_bad_raw_frames_are_refused(case, good_frames, tmp_path):
    _run(case, _copy(good_frames, tmp_path))


# -- contractions.csv (read with the whole take: load_take_dir) --------------------------------------------------

_CONTRACTIONS = "contractions.csv"
_API_CASES = [
    Case("contractions-missing", _remove(_CONTRACTIONS), (), ("contractions.csv", "not found")),
    Case("contractions-ragged", _line(_CONTRACTIONS, 3, "1,1,1.0167,0.1"), (), ("contractions.csv", "line 3")),
    Case("contractions-not-a-number", _line(_CONTRACTIONS, 4, "2,2,1.0333,0.2,x,0.1,0.2"), (),
         ("contractions.csv", "line 4, column 5 (m1)")),
    Case("contractions-header", _line(_CONTRACTIONS, 1, "frame,seq,t,m0,m2,error_upper_mm,error_lower_mm"), (),
         ("contractions.csv", "line 1", "m2")),
    Case("contractions-empty-seq", _line(_CONTRACTIONS, 2, "0,,1.0,0.0,0.2,0.1,0.2"), (),
         ("contractions.csv", "line 2, column 2 (seq)")),
    Case("displacements-not-a-number", _line("displacements.csv", 3, "1,1,1.0167,0.5,1.0,1.5,0.5,0.5,oops"), (),
         ("displacements.csv", "line 3, column 9 (b_z)")),
]


@pytest.mark.parametrize("case", _API_CASES, ids=lambda c: c.id)
def test_a_bad_take_directory_csv_is_refused_by_the_loader(case, good_take, tmp_path):
    folder = _copy(good_take, tmp_path)
    case.damage(folder)
    before = _hashes(folder)
    with pytest.raises(InputError) as error:
        load_take_dir(folder)
    for piece in case.expect:
        assert piece in str(error.value)
    assert _hashes(folder) == before


# -- marker files (C3D, TRC, CSV) through `livebridge take show` -------------------------------------------------

def _c3d_in(units: str, labels=MARKERS) -> Callable[[Path], None]:
    """Rewrite good.c3d as py-c3d writes a file whose POINT:UNITS is ``units`` and POINT:LABELS ``labels``."""
    def damage(folder: Path) -> None:
        import warnings

        import c3d

        writer = c3d.Writer(point_rate=60.0, point_scale=-1.0, point_units=units)
        writer.set_point_labels(list(labels))
        writer.add_frames([(np.ones((2, 5)), np.zeros((0, 0)))] * 3)
        with open(folder / "good.c3d", "wb") as handle, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            writer.write(handle)
    return damage


def _c3d_labels(labels) -> Callable[[Path], None]:
    return _c3d_in("mm", labels)


_SHOW_CSV = ("take", "show", "{dir}/good.csv")
_SHOW_TRC = ("take", "show", "{dir}/good.trc")
_SHOW_C3D = ("take", "show", "{dir}/good.c3d")
_CSV_FILE, _TRC_FILE = "good.csv", "good.trc"
_MARKER_FILE_CASES = [
    Case("csv-ragged-row", _line(_CSV_FILE, 3, "0.1,1,2,3"), _SHOW_CSV, ("good.csv", "line 3", "4 fields")),
    Case("csv-not-a-number", _line(_CSV_FILE, 3, "0.02,1,abc,3,4,5,6"), _SHOW_CSV,
         ("good.csv", "line 3, column 3 (a_y)", "abc")),
    Case("csv-infinite", _line(_CSV_FILE, 4, "0.04,1,2,inf,4,5,6"), _SHOW_CSV, ("good.csv", "line 4, column 4 (a_z)")),
    Case("csv-two-coordinates", _line(_CSV_FILE, 1, "time,a_x,a_y,q,b_x,b_y,b_z"), _SHOW_CSV,
         ("good.csv", "line 1, column 2 (a_x)", "'a' has no z")),
    Case("csv-no-markers", _line(_CSV_FILE, 1, "time,p,q,r,s,u,v"), _SHOW_CSV, ("good.csv", "line 1", "no marker")),
    Case("csv-names-are-case-sensitive", _line(_CSV_FILE, 1, "time,a_x,a_y,a_z,A_X,b_y,b_z"), _SHOW_CSV,
         ("good.csv", "line 1, column 5 (A_X)", "'A' has no y or z")),
    Case("csv-duplicate-name", _line(_CSV_FILE, 1, "time,a_x,a_y,a_z,a_x,b_y,b_z"), _SHOW_CSV,
         ("good.csv", "line 1, column 5 (a_x)", "two columns for 'a' x")),
    Case("csv-time-backwards", _line(_CSV_FILE, 4, "0.0,1,2,3,4,5,6"), _SHOW_CSV,
         ("good.csv", "line 4, column 1 (time)", "does not increase")),
    Case("csv-empty-time", _line(_CSV_FILE, 4, ",1,2,3,4,5,6"), _SHOW_CSV, ("good.csv", "line 4, column 1 (time)")),
    Case("csv-frames-need-a-rate", _edit(_CSV_FILE, "time,", "frame,"), _SHOW_CSV, ("good.csv", "line 1", "--rate")),
    Case("csv-empty", _write(_CSV_FILE, ""), _SHOW_CSV, ("good.csv", "empty file")),
    Case("csv-header-only", _write(_CSV_FILE, "time,a_x,a_y,a_z\n"), _SHOW_CSV, ("good.csv", "line 2", "no frames")),
    Case("csv-not-utf8", _write(_CSV_FILE, b"time,a_x\xff\n"), _SHOW_CSV, ("good.csv", "UTF-8")),
    Case("csv-openface-two-faces", _write(_CSV_FILE, "frame, face_id, timestamp, success, x_0, X_0, Y_0, Z_0\n"
                                                     "1, 0, 0.0, 1, 5, 1, 2, 3\n1, 1, 0.0, 1, 5, 1, 2, 3\n"),
         _SHOW_CSV, ("good.csv", "column 2 (face_id)", "2 faces")),
    Case("csv-bad-units", _nothing, (*_SHOW_CSV, "--units", "furlong"), ("--units", "furlong")),
    Case("csv-bad-rate", _nothing, (*_SHOW_CSV, "--rate", "nan"), ("--rate", "nan")),
    Case("csv-rate-contradicts-times", _nothing, (*_SHOW_CSV, "--rate", "30"), ("good.csv", "rate", "contradicts")),
    Case("trc-bad-header", _line(_TRC_FILE, 1, "hello"), _SHOW_TRC, ("good.trc", "line 1", "PathFileType")),
    Case("trc-no-units-key", _line(_TRC_FILE, 2, "DataRate\tCameraRate\tNumFrames\tNumMarkers"), _SHOW_TRC,
         ("good.trc", "line 2", "no Units")),
    Case("trc-bad-units", _edit(_TRC_FILE, "\tmm\t", "\tfurlong\t"), _SHOW_TRC,
         ("good.trc", "line 3 (Units)", "unknown unit 'furlong'")),
    Case("trc-units-contradicted", _nothing, (*_SHOW_TRC, "--units", "m"), ("good.trc", "line 3 (Units)", "says")),
    Case("trc-bad-rate", _edit(_TRC_FILE, "60.000000\t", "fast\t"), _SHOW_TRC,
         ("good.trc", "line 3, column 1 (DataRate)")),
    Case("trc-marker-count", _edit(_TRC_FILE, "\t8\t2\tmm", "\t8\t3\tmm"), _SHOW_TRC,
         ("good.trc", "line 4", "NumMarkers 3")),
    Case("trc-no-markers", _line(_TRC_FILE, 4, "Frame#\tTime"), _SHOW_TRC, ("good.trc", "line 4", "no markers")),
    Case("trc-duplicate-names", _line(_TRC_FILE, 4, "Frame#\tTime\ta\t\t\ta\t\t"), _SHOW_TRC,
         ("good.trc", "line 4, column 6", "'a' repeats")),
    Case("trc-ragged-row", _line(_TRC_FILE, 8, "2\t0.0166\t1\t2"), _SHOW_TRC, ("good.trc", "line 8", "4 fields")),
    Case("trc-not-a-number", _line(_TRC_FILE, 8, "2\t0.02\t1\tx\t3\t4\t5\t6"), _SHOW_TRC,
         ("good.trc", "line 8, column 4 (a Y)")),
    Case("trc-time-backwards", _line(_TRC_FILE, 9, "3\t0.0\t1\t2\t3\t4\t5\t6"), _SHOW_TRC,
         ("good.trc", "line 9, column 2 (Time)")),
    Case("trc-cut-short", _truncate(_TRC_FILE, 0.1), _SHOW_TRC, ("good.trc", "cut short")),
    Case("c3d-truncated", _truncate("good.c3d", 0.8), _SHOW_C3D, ("good.c3d", "truncated", "frame")),
    Case("c3d-not-a-c3d", _write("good.c3d", b"PK\x03\x04" * 300), _SHOW_C3D, ("good.c3d", "not a C3D")),
    Case("c3d-empty", _write("good.c3d", b""), _SHOW_C3D, ("good.c3d", "not a C3D")),
    Case("c3d-unknown-processor", _c3d_byte(_processor_byte, 0), _SHOW_C3D,
         ("good.c3d", "not a C3D", "processor type")),
    Case("c3d-parameters-at-block-0", _c3d_byte(0, 0), _SHOW_C3D, ("good.c3d", "not a C3D")),
    Case("c3d-unknown-unit", _c3d_in("in"), _SHOW_C3D, ("good.c3d", "POINT:UNITS", "unknown unit 'in'")),
    Case("c3d-repeated-label", _c3d_labels(["a", "a "]), _SHOW_C3D, ("good.c3d", "POINT:LABELS", "'a' repeats")),
    Case("unknown-suffix", _write("good.xyz", "1,2,3\n"), ("take", "show", "{dir}/good.xyz"),
         ("good.xyz", "unknown marker-file type")),
    Case("show-missing-file", _nothing, ("take", "show", "{dir}/none.csv"), ("none.csv", "not found")),
]


@pytest.fixture(scope="module")
def good_marker_files(tmp_path_factory) -> Path:
    from livebridge.take.trajectories import Trajectories, write_trajectories

    folder = tmp_path_factory.mktemp("marker-files")
    points = np.array([_values(k)[1] for k in range(N_FRAMES)])
    short = Trajectories(MARKERS, np.arange(N_FRAMES) / 60, points)
    write_trajectories(folder / "good.csv", short)
    write_trajectories(folder / "good.trc", short)
    long = np.concatenate([points] * 40)  # enough frames that a cut lands inside the point data
    write_trajectories(folder / "good.c3d", Trajectories(MARKERS, np.arange(len(long)) / 60, long))
    return folder


@pytest.mark.parametrize("case", _MARKER_FILE_CASES, ids=lambda c: c.id)
def test_a_bad_marker_file_is_one_error_line(case, good_marker_files, tmp_path):
    output = _run(case, _copy(good_marker_files, tmp_path))
    assert [line.startswith("Error:") for line in output.splitlines()].count(True) == 1, output


def test_the_good_marker_files_show(good_marker_files):
    for name in ("good.csv", "good.trc", "good.c3d"):
        result = CliRunner().invoke(main, ["take", "show", str(good_marker_files / name)])
        assert result.exit_code == 0 and "markers: 2" in result.output, result.output


def test_the_corpus_size():
    """The number of malformed cases this file runs (quoted in the issue's note)."""
    cli = len(_TAKE_DIR_CASES) + len(_OPTION_CASES) + len(_NPZ_CASES) + len(_RAW_CASES) + 1  # + the failed write
    cli += len(_MARKER_FILE_CASES)
    assert cli >= 100 and len(_API_CASES) == 6

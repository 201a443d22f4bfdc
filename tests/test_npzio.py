"""Every .npz a user gives (basis, take, markerless model, ARKit shapes) is read by one reader: a damaged file is
one error naming it, and the file is closed whatever happens."""

from __future__ import annotations

import gc
import io
import warnings

import numpy as np
import pytest

from livebridge.arkit.shapes import load_arkit_shapes
from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.basis_import import import_basis
from livebridge.markerless.model import MarkerlessModel
from livebridge.take.npz import Take


def _import_archive(path):
    return import_basis("choe-ko-ict", path)


LOADERS = [(Basis.load, "livebridge basis", "manifest"), (Take.load, "livebridge take", "manifest"),
           (MarkerlessModel.load, "markerless model", "manifest"), (load_arkit_shapes, "named shapes", "names"),
           (_import_archive, "shape archive", "names")]
"""Each reader, what it says a bad file is not, and an array it reads."""


def _flagged(flag: int, member: str = "manifest") -> bytes:
    """A .npz of a few arrays whose ``member`` has the general-purpose ``flag`` set in its central-directory
    entry (what zipfile reads the member's flags from)."""
    buffer = io.BytesIO()
    np.savez(buffer, manifest=np.array("{}"), names=np.array(["a"]), deltas=np.zeros((1, 2, 3)))
    data = bytearray(buffer.getvalue())
    entry = data.index(b"PK\x01\x02")
    name_end = entry + 46 + int.from_bytes(data[entry + 28:entry + 30], "little")
    while data[entry + 46:name_end] != f"{member}.npy".encode():
        entry = data.index(b"PK\x01\x02", entry + 4)
        name_end = entry + 46 + int.from_bytes(data[entry + 28:entry + 30], "little")
    data[entry + 8:entry + 10] = (int.from_bytes(data[entry + 8:entry + 10], "little") | flag).to_bytes(2, "little")
    return bytes(data)


@pytest.mark.parametrize("load,what,member", LOADERS)
@pytest.mark.parametrize("flag,why", [(0x40, "strong encryption"), (0x01, "password")])
def test_a_member_flagged_encrypted_is_refused_naming_the_file_and_array(tmp_path, load, what, member, flag, why):
    """zipfile refuses such a member with NotImplementedError or RuntimeError, which were internal errors."""
    path = tmp_path / "flagged.npz"
    path.write_bytes(_flagged(flag, member))
    with pytest.raises(InputError, match=why) as caught:
        load(path)
    assert "flagged.npz" in str(caught.value) and member in str(caught.value)


@pytest.mark.parametrize("load,what,member", LOADERS)
def test_a_damaged_npz_is_refused_and_closed(tmp_path, load, what, member):
    """A zip whose central directory is cut off: numpy opened the file, failed and left it open (a
    ResourceWarning when collected)."""
    path = tmp_path / "cut.npz"
    path.write_bytes(_flagged(0)[:-30])
    gc.collect()  # what earlier tests left to the collector warns now, not below
    with warnings.catch_warnings(record=True) as caught_warnings:
        warnings.simplefilter("always")
        with pytest.raises(InputError, match=f"not a {what} .npz") as caught:
            load(path)
        gc.collect()
    assert "cut.npz" in str(caught.value)
    assert not [w for w in caught_warnings if issubclass(w.category, ResourceWarning) and "cut.npz" in str(w.message)]


@pytest.mark.parametrize("change,words", [
    (lambda arrays: {**arrays, "deltas": np.array(["x", "y"])}, ("deltas", "expected numbers")),
    (lambda arrays: {k: v for k, v in arrays.items() if k != "neutral"}, ("neutral", "missing array")),
])
def test_a_shape_archive_with_text_or_a_missing_array_is_refused_naming_it(tmp_path, change, words):
    """`basis import` from an archive of named deltas (ICT-FaceKit's face_region.npz layout): text where numbers
    belong was converted inside the reader's catch-all, and is now named."""
    arrays = {"names": np.array(["a"]), "deltas": np.zeros((1, 3, 3)), "neutral": np.zeros((3, 3)),
              "triangles": np.array([[0, 1, 2]])}
    np.savez(tmp_path / "shapes.npz", **change(arrays))
    with pytest.raises(InputError) as caught:
        _import_archive(tmp_path / "shapes.npz")
    assert all(word in str(caught.value) for word in ("shapes.npz", *words)), str(caught.value)


def test_the_arrays_asked_for_and_with_others_every_other_one_too(tmp_path):
    from livebridge.npzio import read_npz

    np.savez(tmp_path / "a.npz", manifest=np.array("{}"), t=np.zeros(3), extra=np.ones(2))
    assert set(read_npz(tmp_path / "a.npz", "test", ("manifest", "t"))) == {"manifest", "t"}
    assert set(read_npz(tmp_path / "a.npz", "test", ("manifest", "t"), others=True)) == {"manifest", "t", "extra"}
    with pytest.raises(InputError, match="missing array 'missing'") as error:
        read_npz(tmp_path / "a.npz", "test", ("manifest", "missing"), others=True)
    assert error.value.field == "missing"

"""``[face] display``: the render client shows a retargeted face driven by the solving basis's contractions."""

from __future__ import annotations

import numpy as np
import pytest

from livebridge.errors import InputError
from livebridge.face.builtin import builtin_basis
from livebridge.output.render_server import encode_mesh
from livebridge.runtime.build import display_face
from livebridge.runtime.session import session_from_dict


def _session(tmp_path, display):
    return session_from_dict({"cameras": {"urls": ["sim://rig?cameras=2&seed=1"]}, "face": {"display": display}},
                             tmp_path / "session.toml")


def test_the_display_face_replaces_the_solving_basis_in_the_render_mesh(tmp_path):
    basis = builtin_basis()
    shown = basis.with_elements(basis.elements * 0.5)  # any basis with the same muscles
    shown.save(tmp_path / "target.npz")
    session = _session(tmp_path, "target.npz")
    assert session.display == tmp_path / "target.npz"
    face = display_face(session, basis)
    assert face.names == basis.names and np.allclose(face.elements, shown.elements)
    assert encode_mesh(face) == encode_mesh(shown)
    without = session_from_dict({"cameras": {"urls": ["sim://rig"]}}, tmp_path / "s.toml")
    assert without.display is None and display_face(without, basis) is basis


def test_a_display_face_with_other_muscles_is_refused_naming_the_file(tmp_path):
    from livebridge.face.basis import Basis

    basis = builtin_basis()
    Basis(basis.neutral, basis.triangles, basis.elements[:2], basis.muscles[:2]).save(tmp_path / "two.npz")
    with pytest.raises(InputError) as error:
        display_face(_session(tmp_path, "two.npz"), basis)
    assert "two.npz" in str(error.value) and "display" in str(error.value)
    with pytest.raises(InputError, match="face.display"):
        _session(tmp_path, "target.obj")

"""An expression scan of another face than the neutral's is told: its registered skin lies off the neutral's
surface by more than the scan's noise explains (:mod:`livebridge.retarget.same_face`)."""

from __future__ import annotations

import dataclasses
import math

import pytest
from factories import run_retarget_scans, write_builtin_scans

from livebridge.retarget.same_face import GAP_FLOOR_MM, GAP_NOISES, another_face


@pytest.mark.parametrize("gap,noise,told", [
    (0.3, 0.28, False), (0.55, 0.28, False), (0.6, 0.28, True),  # the noise's limit, 0.56 mm
    (0.45, 0.02, False), (0.55, 0.02, True),  # a mesh's samples: the floor
    (0.55, float("nan"), True), (float("nan"), 0.2, False),
])
def test_another_face_is_told_past_the_noise_and_the_floor(gap, noise, told):
    why = another_face(gap, noise)
    assert (why is not None) == told
    if told:
        limit = GAP_FLOOR_MM if math.isnan(noise) else max(GAP_NOISES * noise, GAP_FLOOR_MM)
        assert f"{gap:.2f} mm" in why and f"{limit:.2f} mm" in why
        assert "another person" in why and "more than one muscle" in why


def test_retarget_scans_warns_of_an_expression_of_another_face(tmp_path):
    """The built-in face's smile is its own; a smile of the built-in face under the known warp of `livebridge
    bench retarget` (other proportions) is another face's: told, naming the expression and its file (its shape
    difference, built in as motion, also reads as a smile of both sides), and the basis is still written."""
    from livebridge.bench.retarget import known_warp
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.landmarks import load_landmark_set

    write_builtin_scans(tmp_path, 6, {"neutral": "neutral", "zygomatic_major_L": "smile_L"})
    basis = builtin_basis()
    landmarks = load_landmark_set("builtin-22").as_dict(basis.neutral, basis.triangles)
    other = dataclasses.replace(basis, neutral=known_warp(basis.neutral, landmarks))
    write_builtin_scans(tmp_path, 7, {"zygomatic_major_R": "other_smile_R"}, basis=other)
    result = run_retarget_scans(tmp_path, "neutral.ply", {"zygomatic_major_L": "smile_L.ply",
                                                          "zygomatic_major_R": "other_smile_R.ply"})
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.output.splitlines() if line.startswith("warning:")]
    told = [line for line in warnings if "registered on the neutral" in line]
    assert len(told) == 1 and told[0].startswith("warning: zygomatic_major_R (other_smile_R.ply):"), result.output
    assert not any("zygomatic_major_L" in line for line in warnings), result.output
    assert (tmp_path / "basis.npz").exists()

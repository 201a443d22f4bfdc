"""Landmark files as people pick them on scans: MeshLab PickPoints files (.pp) and templates (.pptpl), read
by `landmarks place` and `retarget scans` like the CSV and TOML ones. (Malformed files: test_bad_input.py.)"""

from __future__ import annotations

import shutil
from xml.etree import ElementTree

import numpy as np
import pytest
from click.testing import CliRunner
from factories import assert_cli_refused, write_builtin_scans

from livebridge.cli import main
from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.builtin import builtin_basis
from livebridge.retarget.eyelids import LID_LANDMARK_NAMES
from livebridge.retarget.landmarks import THESIS_22_NAMES, load_landmark_set
from livebridge.retarget.point_files import read_points, write_pick_template

# A file as MeshLab 2023.12's PickPoints editor saves one (QDomDocument, indent 1, attributes x y z active name)
MESHLAB_PP = """<!DOCTYPE PickedPoints>
<PickedPoints>
 <DocumentData>
  <DateTime time="14:02:11" date="2026-11-30"/>
  <User name="ana"/>
  <DataFileName name="smile.ply"/>
  <templateName name="livebridge-22"/>
 </DocumentData>
 <point x="31.5" y="44.25" z="88" active="1" name="brow_outer_L"/>
 <point x="0" y="-3.25e-05" z="120.125" active="1" name="nose_tip"/>
 <point x="0" y="0" z="0" active="0" name="lm_37"/>
 <point x="-2" y="-80.5" z="89.75" name="chin"/>
</PickedPoints>
"""


def test_picked_points_are_read_as_meshlab_writes_them_skipping_the_unpicked(tmp_path):
    path = tmp_path / "smile_picked_points.pp"
    path.write_text(MESHLAB_PP)
    points = read_points(path)
    assert list(points) == ["brow_outer_L", "nose_tip", "chin"]  # file order; lm_37 was not picked (active="0")
    assert np.array_equal(points["nose_tip"], [0.0, -3.25e-05, 120.125])
    assert np.array_equal(points["chin"], [-2.0, -80.5, 89.75])  # no active attribute: picked, as in MeshLab


@pytest.mark.parametrize("lids", [False, True])
def test_landmarks_template_lists_the_names_to_pick_in_order(tmp_path, lids):
    out = tmp_path / "face.pptpl"
    result = CliRunner().invoke(main, ["landmarks", "template", "--out", str(out)] + ["--lids"] * lids)
    assert result.exit_code == 0, result.output
    assert out.read_text().splitlines()[0] == "<!DOCTYPE PickPointsTemplate>"
    root = ElementTree.parse(out).getroot()
    assert root.tag == "PickPointsTemplate"
    names = [point.get("name") for point in root.findall("point")]
    lid_names = sorted(LID_LANDMARK_NAMES)
    assert names == list(THESIS_22_NAMES) + lid_names * lids
    assert len(names) == (30 if lids else 22) and f"{len(names)} names" in result.output


def test_template_names_survive_xml_quoting(tmp_path):
    names = ['a "quoted" name', "R&D <left>", "lm_37"]
    write_pick_template(tmp_path / "t.pptpl", names)
    assert [p.get("name") for p in ElementTree.parse(tmp_path / "t.pptpl").getroot().findall("point")] == names


def _builtin_points(names) -> dict:
    from livebridge.face.builtin import builtin_basis

    face = builtin_basis()
    placed = load_landmark_set("builtin-22").as_dict(face.neutral, face.triangles)
    return {name: placed[name] + [0.0, 0.0, 0.4] for name in names}  # a little off the surface, as clicked


def _write_pp(path, points, unpicked=()) -> None:
    rows = [f' <point x="{x}" y="{y}" z="{z}" active="1" name="{name}"/>' for name, (x, y, z) in _texts(points)]
    rows += [f' <point x="0" y="0" z="0" active="0" name="{name}"/>' for name in unpicked]
    path.write_text("<!DOCTYPE PickedPoints>\n<PickedPoints>\n" + "\n".join(rows) + "\n</PickedPoints>\n")


def _write_csv(path, points) -> None:
    path.write_text("name,x,y,z\n" + "".join(f"{name},{x},{y},{z}\n" for name, (x, y, z) in _texts(points)))


def _texts(points):
    """(name, coordinate texts) that read back to the same doubles."""
    return [(name, [repr(float(v)) for v in xyz]) for name, xyz in points.items()]


def test_landmarks_place_puts_picked_points_where_the_same_csv_puts_them(tmp_path):
    points = _builtin_points(THESIS_22_NAMES)
    _write_csv(tmp_path / "lm.csv", points)
    _write_pp(tmp_path / "lm.pp", points, unpicked=("lm_37", "lm_38"))
    for name in ("lm.csv", "lm.pp"):
        result = CliRunner().invoke(main, ["landmarks", "place", "builtin", "--points", str(tmp_path / name),
                                           "--out", str(tmp_path / f"{name}.toml"), "--require-22"])
        assert result.exit_code == 0, result.output
    assert (tmp_path / "lm.pp.toml").read_bytes() == (tmp_path / "lm.csv.toml").read_bytes()


@pytest.fixture(scope="module")
def scan_folder(tmp_path_factory):
    """A neutral and a jaw scan of the built-in face (8000 points, no colour) with CSV landmark files."""
    folder = tmp_path_factory.mktemp("picked")
    write_builtin_scans(folder, 5, {"neutral": "neutral", "jaw": "jaw"})
    return folder


def _scans(folder, neutral_landmarks: str, *extra):
    return CliRunner().invoke(main, [
        "retarget", "scans", "--neutral", str(folder / "neutral.ply"), "--neutral-landmarks",
        str(folder / neutral_landmarks), "--expression", f"jaw={folder / 'jaw.ply'}", "--grid", "40x40",
        "--out", str(folder / "b.npz"), *extra])


def test_retarget_scans_reads_meshlab_picked_points_and_finds_them_by_meshlabs_name(tmp_path, scan_folder):
    from livebridge.retarget.point_files import read_points_csv

    with_csv = tmp_path / "csv"
    shutil.copytree(scan_folder, with_csv)
    result = _scans(with_csv, "neutral.landmarks.csv")
    assert result.exit_code == 0, result.output
    picked = tmp_path / "picked"  # the CSVs as MeshLab files: the neutral's named, the jaw's found by default
    picked.mkdir()
    for name in ("neutral", "jaw"):
        shutil.copy(scan_folder / f"{name}.ply", picked)
        _write_pp(picked / f"{name}_picked_points.pp", read_points_csv(scan_folder / f"{name}.landmarks.csv"))
    result = _scans(picked, "neutral_picked_points.pp")
    assert result.exit_code == 0, result.output
    built, expected = Basis.load(picked / "b.npz"), Basis.load(with_csv / "b.npz")
    assert np.array_equal(built.neutral, expected.neutral)
    assert np.array_equal(built.elements, expected.elements)
    assert np.abs(built.elements).max() > 5  # the jaw opened


def test_retarget_scans_without_an_expressions_landmarks_names_both_files_it_looked_for(tmp_path, scan_folder):
    shutil.copytree(scan_folder, tmp_path, dirs_exist_ok=True)
    (tmp_path / "jaw.landmarks.csv").unlink()
    result = _scans(tmp_path, "neutral.landmarks.csv")
    assert_cli_refused(result, "--expression", "jaw.landmarks.csv", "jaw_picked_points.pp", "SCAN:LANDMARKS")
    assert not (tmp_path / "b.npz").exists()


def test_retarget_scans_finds_the_neutrals_landmarks_as_it_finds_an_expressions(tmp_path, scan_folder):
    shutil.copytree(scan_folder, tmp_path / "found")
    common = ["retarget", "scans", "--expression", f"jaw={tmp_path / 'found' / 'jaw.ply'}", "--grid", "40x40"]
    found = CliRunner().invoke(main, [*common, "--neutral", str(tmp_path / "found" / "neutral.ply"),
                                      "--out", str(tmp_path / "found.npz")])
    assert found.exit_code == 0, found.output
    result = _scans(tmp_path / "found", "neutral.landmarks.csv")
    assert result.exit_code == 0, result.output
    built, named = (Basis.load(path).elements for path in (tmp_path / "found.npz", tmp_path / "found" / "b.npz"))
    assert np.array_equal(built, named)
    (tmp_path / "found" / "neutral.landmarks.csv").unlink()
    missing = CliRunner().invoke(main, [*common, "--neutral", str(tmp_path / "found" / "neutral.ply"),
                                        "--out", str(tmp_path / "missing.npz")])
    assert_cli_refused(missing, "--neutral-landmarks", "neutral.landmarks.csv", "neutral_picked_points.pp")
    assert not (tmp_path / "missing.npz").exists()


@pytest.mark.parametrize("suffix", [".csv", ".toml"])
def test_a_byte_order_mark_is_no_part_of_the_first_landmark(tmp_path, suffix):
    """Excel and Windows Notepad save UTF-8 with a byte order mark: the first row's name (or a CSV header) must
    read as written, not as '\\ufeffnose_tip' (a landmark then missing, or an unknown one quietly dropped)."""
    text = {".csv": "name,x,y,z\nnose_tip,0,0,120\nchin,0,-80,90\n",
            ".toml": "nose_tip = [0, 0, 120]\nchin = [0, -80, 90]\n"}[suffix]
    path = tmp_path / f"lm{suffix}"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    points = read_points(path)
    assert list(points) == ["nose_tip", "chin"]
    np.testing.assert_array_equal(points["chin"], [0, -80, 90])
    headless = tmp_path / "headless.csv"
    headless.write_bytes(b"\xef\xbb\xbfnose_tip,0,0,120\n")
    assert list(read_points(headless)) == ["nose_tip"]


def test_a_point_cloud_with_a_byte_order_mark_reads_its_first_point(tmp_path):
    from livebridge.retarget.scan import read_scan

    path = tmp_path / "cloud.xyz"
    rows = "".join(f"{k} {2 * k} {3 * k}\n" for k in range(5))
    path.write_bytes(b"\xef\xbb\xbf" + rows.encode())
    np.testing.assert_array_equal(read_scan(path).points, [[k, 2 * k, 3 * k] for k in range(5)])


def test_points_and_landmark_sets_given_for_each_other_say_which_is_which(tmp_path):
    """A CSV of points where a landmark set (on a mesh) is wanted, and the reverse, as a user mixes them up:
    each is refused by name with the command that turns one into the other, not as malformed TOML."""
    truth = load_landmark_set("builtin-22")
    face = builtin_basis()
    points = truth.positions(face.neutral, face.triangles)
    (tmp_path / "points.csv").write_text("".join(f"{n},{x!r},{y!r},{z!r}\n" for n, (x, y, z) in
                                                 zip(truth.names, points.tolist())))
    result = CliRunner().invoke(main, ["landmarks", "show", "builtin", str(tmp_path / "points.csv"), "--out",
                                       str(tmp_path / "lm.png")])
    assert_cli_refused(result, "points.csv", "not a landmark set", "landmarks place MESH --points points.csv")
    truth.save(tmp_path / "set.toml")
    with pytest.raises(InputError, match="placed on a mesh .* not points"):
        read_points(tmp_path / "set.toml")

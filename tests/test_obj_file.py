"""The bulk OBJ parser reads a scanner's regular layout exactly as the line-by-line reader does, and leaves every
other layout to it (which names the line at fault)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from livebridge.face.obj_file import read_obj_bulk, read_obj_lines

FORMS = {"a": "{v}", "a/b": "{v}/{t}", "a//c": "{v}//{n}", "a/b/c": "{v}/{t}/{n}"}


def _obj(form: str, rng: np.random.Generator, colours: bool = False, polygons=(3,), crlf: bool = False,
         texcoord_w: bool = False) -> bytes:
    """An OBJ of 60 vertices and 40 faces of ``polygons`` corners in ``form``, two materials, comments, groups
    and normals between."""
    lines = ["# scanner export", "mtllib skin.mtl", "o face"]
    for _ in range(60):
        x, y, z = rng.normal(0, 30, 3)
        lines.append(f"v {x:.6f} {y:.6f} {z:.6f}" + (f" {rng.integers(0, 256)} {rng.integers(0, 256)} 7" if colours
                                                      else ""))
        lines.append(f"vt {rng.random():.5f} {rng.random():.5f}" + (" 0" if texcoord_w else ""))
        lines.append("vn 0 0 1")
    for k in range(40):
        if k % 13 == 0:
            lines += ["g part", f"usemtl skin_{k % 2}", "s 1"]
        n = polygons[k % len(polygons)]
        corners = rng.choice(60, n, replace=False) + 1
        lines.append("f " + " ".join(FORMS[form].format(v=c, t=c, n=c) for c in corners))
    return (("\r\n" if crlf else "\n").join(lines) + "\n").encode()


def _same(a, b) -> None:
    assert np.array_equal(a.points, b.points)
    assert (a.colours is None and b.colours is None) or np.array_equal(a.colours, b.colours)
    assert np.array_equal(a.texcoords, b.texcoords)
    assert np.array_equal(a.triangles, b.triangles) and np.array_equal(a.corner_uv, b.corner_uv)
    assert a.face_material == b.face_material and a.libraries == b.libraries


@pytest.mark.parametrize("form", sorted(FORMS))
@pytest.mark.parametrize("layout", [dict(), dict(colours=True), dict(polygons=(3, 4, 5)), dict(crlf=True),
                                    dict(texcoord_w=True, polygons=(4,))])
def test_the_regular_layouts_are_read_in_bulk_as_line_by_line(form, layout):
    data = _obj(form, np.random.default_rng(len(form)), **layout)
    bulk = read_obj_bulk(data)
    assert bulk is not None
    _same(bulk, read_obj_lines(data, Path("scan.obj")))
    assert len(bulk.triangles) == sum(p - 2 for p in [layout.get("polygons", (3,))[k % len(layout.get(
        "polygons", (3,)))] for k in range(40)])


def _spoil(text: str) -> list[tuple[str, str]]:
    first_face = next(line for line in text.splitlines() if line.startswith("f "))
    first_vertex = next(line for line in text.splitlines() if line.startswith("v "))
    return [
        ("a relative index", text.replace(first_face, "f -1 -2 -3")),
        ("a face before its vertices", first_face + "\n" + text),
        ("tabs", text.replace(first_vertex, first_vertex.replace(" ", "\t"))),
        ("a leading blank", text.replace(first_vertex, " " + first_vertex)),
        ("a vertex's w", text.replace(first_vertex, first_vertex + " 1.0")),
        ("corners written two ways", text.replace(first_face, first_face.replace("/", "//", 1))),
        ("a vertex not finite", text.replace(first_vertex, "v nan 0 0")),
        ("a number with an underscore", text.replace(first_vertex, "v 1_0 0 0")),
        ("index 0", text.replace(first_face, "f 0/1 1/1 2/2")),
        ("an index past the vertices", text.replace(first_face, "f 1/1 2/2 999/3")),
        ("a corner with four fields", text.replace(first_face, "f 1/1/1/1 2/2 3/3")),
        ("a face of two corners", text.replace(first_face, "f 1/1 2/2")),
    ]


@pytest.mark.parametrize("case", range(12))
def test_any_other_layout_is_left_to_the_line_by_line_reader(tmp_path, case):
    from livebridge.errors import InputError
    from livebridge.retarget.scan import read_scan

    regular = _obj("a/b", np.random.default_rng(1)).decode().replace("mtllib skin.mtl\n", "")  # no MTL to find
    name, text = _spoil(regular)[case]
    assert read_obj_bulk(text.encode()) is None, name
    path = tmp_path / "scan.obj"
    path.write_text(text)
    try:
        expected = read_obj_lines(text.encode(), path)
    except InputError as error:
        with pytest.raises(InputError) as raised:
            read_scan(path)
        assert str(raised.value) == str(error) and "line" in str(error)  # the line-by-line reader's error
        return
    scan = read_scan(path)  # read all the same: the line-by-line reader takes such files
    assert np.array_equal(scan.points, expected.points) and np.array_equal(scan.triangles, expected.triangles)


def test_a_mesh_reads_the_same_with_a_byte_order_mark_tabs_and_indented_lines(tmp_path):
    """A target mesh (``read_obj``) goes through the scans' reader: a UTF-8 byte order mark, tab separators and
    indented lines (which the mesh reader used to read as no vertices, or one vertex short) change nothing."""
    from livebridge.face.builtin import builtin_basis
    from livebridge.face.meshio import read_obj

    face = builtin_basis()
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in face.neutral]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in face.triangles]
    plain = tmp_path / "plain.obj"
    plain.write_text("\n".join(lines) + "\n")
    odd = tmp_path / "odd.obj"
    odd.write_bytes(b"\xef\xbb\xbf" + "\r\n".join("\t" + line.replace(" ", "\t") for line in lines).encode())
    want, got = read_obj(plain), read_obj(odd)
    np.testing.assert_array_equal(got.vertices, want.vertices)
    np.testing.assert_array_equal(got.triangles, want.triangles)
    assert len(want.vertices) == len(face.neutral) and len(want.triangles) == len(face.triangles)


@pytest.mark.parametrize("form", sorted(FORMS))
def test_a_moved_obj_keeps_everything_but_its_positions_and_normals(form, rng):
    """``ObjLayout``: new positions, the vertex colours, texture coordinates, polygons (quads stay quads),
    groups and materials as written; no normals (they no longer fit the surface), CRLF and a byte order mark
    kept."""
    from livebridge.face.obj_file import _BOM, ObjLayout, read_obj_data

    data = _BOM + _obj(form, rng, colours=True, polygons=(3, 4, 5), crlf=True)
    before = read_obj_data(data, Path("head.obj"))
    moved_to = before.points * 1.5 + rng.normal(0, 1, before.points.shape)
    layout = ObjLayout.of(data)
    out = layout.moved(moved_to)
    after = read_obj_data(out, Path("moved.obj"))
    assert np.allclose(after.points, moved_to, rtol=1e-8, atol=1e-6)
    assert np.array_equal(after.colours, before.colours) and np.array_equal(after.texcoords, before.texcoords)
    assert np.array_equal(after.triangles, before.triangles) and np.array_equal(after.corner_uv, before.corner_uv)
    assert after.face_material == before.face_material and after.libraries == before.libraries
    assert out.startswith(_BOM) and out.count(b"\r\n") == data.count(b"\r\n") - 60  # the 60 vn lines gone
    text = out.decode("utf-8-sig")
    assert "vn " not in text and not any(c.count("/") == 2 for line in text.splitlines() if line.startswith("f ")
                                         for c in line.split()[1:])
    assert [line for line in text.splitlines() if line.startswith(("g ", "s ", "o ", "#"))] == \
        [line for line in data.decode("utf-8-sig").splitlines() if line.startswith(("g ", "s ", "o ", "#"))]
    assert layout.n_vertices == len(before.points)
    for wrong in (moved_to[:-1], np.vstack([moved_to, [[0, 0, 0]]])):  # not this file's vertices
        with pytest.raises(ValueError):
            layout.moved(wrong)


@pytest.mark.parametrize("corners", [3, 4])
@pytest.mark.parametrize("textured", [False, True])
def test_the_writer_s_files_read_back_as_written(corners, textured, rng):
    """Triangles or quads, with per-vertex texture coordinates and a material or plain: read back (in bulk and line
    by line alike) to the same vertices, faces (quads fanned), texture coordinates and material."""
    from livebridge.face.obj_file import mesh_obj, read_obj_data

    vertices = rng.normal(0.0, 50.0, (30, 3))
    faces = np.array([rng.choice(30, corners, replace=False) for _ in range(20)])
    uv = rng.random((30, 2)) if textured else None
    data = mesh_obj(vertices, faces, "a test mesh", uv=uv, material=("skin.mtl", "skin") if textured else None)
    for read in (read_obj_data(data, Path("m.obj")), read_obj_lines(data, Path("m.obj"))):
        assert np.allclose(read.points, vertices, atol=5e-7, rtol=0)
        fanned = faces[:, [0, 1, 2]] if corners == 3 else np.concatenate([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])
        assert sorted(map(tuple, read.triangles)) == sorted(map(tuple, fanned))
        if textured:
            assert np.allclose(read.texcoords, uv, atol=5e-8, rtol=0)
            assert np.array_equal(read.corner_uv, read.triangles)  # one texture coordinate per vertex
            assert read.libraries == ["skin.mtl"] and set(read.face_material) == {"skin"}
        else:
            assert len(read.texcoords) == 0 and (read.corner_uv == -1).all() and read.libraries == []
    assert data.startswith(b"# a test mesh\n")

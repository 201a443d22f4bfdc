"""Small seeded objects for tests."""

from __future__ import annotations

import numpy as np

from livebridge.face.basis import Basis, Muscle


def random_basis(rng: np.random.Generator, n_vertices: int = 40, n_muscles: int = 4) -> Basis:
    """A small random basis on a triangulated grid, for round-trip tests."""
    side = int(np.ceil(np.sqrt(n_vertices)))
    xs, ys = np.meshgrid(np.arange(side), np.arange(side))
    neutral = np.stack([xs.ravel(), ys.ravel(), rng.normal(size=side * side)], axis=1)[: side * side] * 10
    grid = np.arange(side * side).reshape(side, side)
    a, b, c, d = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel(), grid[1:, :-1].ravel(), grid[1:, 1:].ravel()
    triangles = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
    elements = rng.normal(size=(n_muscles, side * side, 3))
    muscles = tuple(Muscle(f"m{i}", "upper" if i % 2 == 0 else "lower", None, "") for i in range(n_muscles))
    return Basis(neutral, triangles, elements, muscles)


def assert_cli_refused(result, *words) -> None:
    """A click ``result`` that exited != 0 with one ``Error:`` line holding every word, and no traceback (nor a
    crash report's internal error)."""
    assert result.exit_code != 0, result.output
    assert "Traceback" not in result.output and "internal error" not in result.output, result.output
    error = next(line for line in result.output.splitlines() if line.startswith("Error:"))
    for word in words:
        assert word in error, (word, error)


def write_builtin_scans(folder, seed: int, stems: dict[str, str], basis=None, colour: bool = False,
                        landmarks: str = "builtin-22", lit: bool = False, n_points: int = 8000, eyes=None) -> None:
    """The built-in face's (or ``basis``'s, on the ``landmarks`` set's topology) neutral and expressions as
    ``n_points``-point scans, without colour unless ``colour`` (shaded by the bench's flash if ``lit``; seeing the
    head's ``eyes`` between the lids, :class:`~livebridge.bench.scan_eyes.Eyeballs`), ``STEM.ply`` (ascii) and
    ``STEM.landmarks.csv`` (``name,x,y,z``; the shipped ``landmarks`` set's points) in ``folder``; ``stems``:
    ``"neutral"`` or a muscle -> file stem."""
    from livebridge.bench.scans import synthetic_scans
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.landmarks import load_landmark_set
    from livebridge.retarget.ply_file import write_ply

    muscles = tuple(name for name in stems if name != "neutral")
    neutral, expressions = synthetic_scans(basis or builtin_basis(), load_landmark_set(landmarks),
                                           np.random.default_rng(seed), n_points=n_points, hole_muscle=None,
                                           colour=colour, muscles=muscles, lit=lit, eyes=eyes)
    for name, stem in stems.items():
        scan = neutral if name == "neutral" else expressions[name]
        write_ply(folder / f"{stem}.ply", scan.points, None, "ascii", scan.colours)
        (folder / f"{stem}.landmarks.csv").write_text("name,x,y,z\n" + "".join(
            f"{k},{float(x)!r},{float(y)!r},{float(z)!r}\n" for k, (x, y, z) in scan.landmarks.items()))


def run_retarget_scans(folder, neutral: str, expressions: dict[str, str], *extra: str, grid: str = "40x40",
                       out: str = "basis.npz"):
    """``livebridge retarget scans`` on scan files in ``folder``: ``neutral`` (its landmarks ``STEM.landmarks.csv``
    beside it) and muscle -> scan file, with a ``grid`` and ``out`` (in ``folder``); the CliRunner's result."""
    from pathlib import Path

    from click.testing import CliRunner

    from livebridge.cli import main

    folder = Path(folder)
    expression_options = [arg for name, scan in expressions.items()
                          for arg in ("--expression", f"{name}={folder / scan}")]
    return CliRunner().invoke(main, [
        "retarget", "scans", "--neutral", str(folder / neutral), "--neutral-landmarks",
        str((folder / neutral).with_suffix(".landmarks.csv")), *expression_options, "--grid", grid,
        "--out", str(folder / out), *extra])


def split_triangles(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every triangle cut in four at its edges' midpoints: the same surface, another (4x denser) topology; the
    first ``len(vertices)`` vertices are the given ones."""
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    unique, index = np.unique(edges, axis=0, return_inverse=True)
    mid = len(vertices) + index.reshape(3, -1).T  # (t, 3): the midpoints of edges ab, bc, ca
    a, b, c = triangles.T
    ab, bc, ca = mid.T
    split = np.concatenate([np.column_stack(t) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return np.vstack([vertices, vertices[unique].mean(axis=1)]), split


def interior_holes(grid) -> np.ndarray:
    """The masked points of a :class:`~livebridge.retarget.grid.FaceGrid` labelled by hole (8-connected), 0 on
    the grid's surface and in the gaps open to its edge; shape (n_rows, n_cols)."""
    from scipy.ndimage import label

    labels, _ = label(~grid.valid, structure=np.ones((3, 3), bool))
    on_edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    labels[np.isin(labels, on_edge)] = 0
    return labels

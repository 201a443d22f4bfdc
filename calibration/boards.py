"""Calibration boards described by one spec string.

Specs
-----
``chessboard:COLSxROWS:SQUARE_MM``
    COLS x ROWS *inner* corners, as OpenCV's pattern size counts them
    (the printed board has (COLS+1) x (ROWS+1) squares).
``charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT[:legacy]``
    COLS x ROWS *squares* (OpenCV >= 4.7 ``CharucoBoard``). ``DICT`` is an ArUco
    dictionary name such as ``DICT_4X4_50`` (the ``DICT_`` prefix is optional).
    ``:legacy`` selects the pre-4.6 layout, for boards printed with older OpenCV
    (it differs only when ROWS is even).

Board frame
-----------
Millimetres; origin at the top-left outer corner of the square grid as printed,
+x along a row to the right, +y down the columns, +z into the paper (so a camera
looking at the printed side sees the board's +z pointing away from it).
``object_points`` are the detectable corners in that frame; corner ``k`` of a
chessboard is OpenCV's ``k``-th corner, of a ChArUco board the corner with id ``k``.

Symmetric chessboards
---------------------
A chessboard's corner grid maps onto itself under a half turn, and a square one
(COLS = ROWS) under quarter turns too. Some of these turns swap the square colours
(the detector tells them apart: corner 0 sits at a dark square); the others
(:meth:`Board.grid_rotations` with ``keeps_colours``) leave the printed board
unchanged, so its corner order in one image is ambiguous: calibration resolves
it across views and cameras (:mod:`livebridge.calibration.orientation`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from livebridge.errors import InputError

_SPEC_HELP = ("expected 'chessboard:COLSxROWS:SQUARE_MM' or "
              "'charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT[:legacy]', e.g. 'charuco:7x5:40:30:DICT_4X4_50'")


@dataclass(frozen=True)
class Board:
    """A planar calibration target.

    Attributes
    ----------
    kind : str
        ``'chessboard'`` or ``'charuco'``.
    cols, rows : int
        Inner corners (chessboard) or squares (ChArUco) along x and y.
    square_mm : float
    marker_mm : float
        ArUco marker side (ChArUco only, else 0).
    dictionary : str
        ArUco dictionary name such as ``'DICT_4X4_50'`` (ChArUco only).
    legacy : bool
        Pre-OpenCV-4.6 ChArUco layout.
    """

    kind: str
    cols: int
    rows: int
    square_mm: float
    marker_mm: float = 0.0
    dictionary: str = ""
    legacy: bool = False

    @property
    def spec(self) -> str:
        """The spec string this board parses from."""
        size = f"{self.cols}x{self.rows}:{_num(self.square_mm)}"
        if self.kind == "chessboard":
            return f"chessboard:{size}"
        return f"charuco:{size}:{_num(self.marker_mm)}:{self.dictionary}" + (":legacy" if self.legacy else "")

    @property
    def squares(self) -> tuple[int, int]:
        """Printed squares along x and y."""
        if self.kind == "chessboard":
            return self.cols + 1, self.rows + 1
        return self.cols, self.rows

    @property
    def size_mm(self) -> tuple[float, float]:
        """Width and height of the square grid in mm."""
        sx, sy = self.squares
        return sx * self.square_mm, sy * self.square_mm

    @property
    def n_corners(self) -> int:
        """Number of detectable corners (ids ``0 .. n_corners-1``)."""
        if self.kind == "chessboard":
            return self.cols * self.rows
        return (self.cols - 1) * (self.rows - 1)

    @property
    def min_corners(self) -> int:
        """Fewest corners a detection needs to be used."""
        return self.n_corners if self.kind == "chessboard" else 6

    @cached_property
    def object_points(self) -> np.ndarray:
        """Corner positions in the board frame (mm), shape (n_corners, 3), z = 0."""
        if self.kind == "chessboard":
            ix, iy = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
            points = np.stack([ix.ravel() + 1, iy.ravel() + 1, np.zeros(ix.size)], axis=1) * self.square_mm
            return points.astype(np.float64)
        return np.asarray(self.cv_board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    @cached_property
    def grid_rotations(self) -> tuple[GridRotation, ...]:
        """Turns of the board about its centre that map the corner grid onto itself, identity first.

        A ChArUco board has only the identity (its markers fix the order).
        """
        if self.kind != "chessboard":
            return (GridRotation(0, np.arange(self.n_corners), np.eye(4), True),)
        turns = (0, 1, 2, 3) if self.cols == self.rows else (0, 2)
        return tuple(_grid_rotation(self, turn) for turn in turns)

    @cached_property
    def cv_board(self):
        """The ``cv2.aruco.CharucoBoard`` (ChArUco only)."""
        if self.kind != "charuco":
            raise AttributeError("a chessboard has no ArUco board")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        board = cv2.aruco.CharucoBoard((self.cols, self.rows), float(self.square_mm), float(self.marker_mm),
                                       dictionary)
        board.setLegacyPattern(self.legacy)
        return board

    def image(self, px_per_square: int, margin_squares: float = 0.5) -> np.ndarray:
        """The board as printed, uint8 grayscale, with a white margin.

        Parameters
        ----------
        px_per_square : int
            Pixels per square side (exact: the grid spans ``squares * px_per_square`` pixels).
        margin_squares : float
            White margin around the grid, in squares.

        Returns
        -------
        ndarray, shape (height, width), uint8; the grid's top-left corner is at pixel
        ``(margin, margin)`` with ``margin = round(margin_squares * px_per_square)``.
        """
        margin = int(round(margin_squares * px_per_square))
        sx, sy = self.squares
        width, height = sx * px_per_square + 2 * margin, sy * px_per_square + 2 * margin
        if self.kind == "charuco":
            return self.cv_board.generateImage((width, height), marginSize=margin, borderBits=1)
        image = np.full((height, width), 255, np.uint8)
        for j in range(sy):
            for i in range(sx):
                if (i + j) % 2 == 0:
                    y0, x0 = margin + j * px_per_square, margin + i * px_per_square
                    image[y0:y0 + px_per_square, x0:x0 + px_per_square] = 0
        return image


@dataclass(frozen=True, eq=False)
class GridRotation:
    """A relabelling of a chessboard's corners by a turn of the board about its centre.

    Attributes
    ----------
    quarter_turns : int
        0..3, about the board's +z (from +x towards +y).
    order : ndarray of int, shape (n_corners,)
        Corner ``k`` relabelled is corner ``order[k]`` as labelled before: ``corners[order]``.
    board_transform : ndarray, shape (4, 4)
        The turn in the board frame: ``object_points[order] == apply(board_transform, object_points)``, so
        a pose ``board2cam`` of the old labelling becomes ``board2cam @ board_transform``.
    keeps_colours : bool
        The printed board looks the same after the turn (so no image tells the labellings apart).
    """

    quarter_turns: int
    order: np.ndarray
    board_transform: np.ndarray
    keeps_colours: bool


def _grid_rotation(board: Board, turn: int) -> GridRotation:
    width, height = board.size_mm
    centre = np.array([width / 2, height / 2, 0.0])
    cos, sin = np.rint(np.cos(turn * np.pi / 2)), np.rint(np.sin(turn * np.pi / 2))
    rotation = np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = centre - rotation @ centre
    points = board.object_points
    turned = points @ rotation.T + transform[:3, 3]
    order = np.argmin(np.linalg.norm(turned[:, None] - points[None], axis=2), axis=1)
    first_square = rotation @ (np.array([0.5, 0.5, 0.0]) * board.square_mm - centre) + centre
    column, row = np.floor(first_square[:2] / board.square_mm).astype(int)
    return GridRotation(turn, order, transform, bool((column + row) % 2 == 0))


MAX_SQUARES = 100
"""The most squares (or inner corners) a board spec has along a side."""


def parse_board(spec: str) -> Board:
    """Parse a board spec string (see the module docstring); bad specs raise :class:`InputError`."""
    if isinstance(spec, Board):
        return spec
    text = str(spec).strip()
    parts = text.split(":")
    kind = parts[0].lower()

    def fail(why: str):
        raise InputError(f"{why}; {_SPEC_HELP}", field=f"board spec {text!r}")

    if kind not in ("chessboard", "charuco"):
        fail(f"unknown board kind {parts[0]!r}")
    expected = (3,) if kind == "chessboard" else (5, 6)
    if len(parts) not in expected:
        fail(f"{kind} needs {' or '.join(map(str, expected))} ':'-separated fields, got {len(parts)}")
    match = re.fullmatch(r"(\d+)[xX](\d+)", parts[1])
    if not match:
        fail(f"size {parts[1]!r} is not COLSxROWS")
    cols, rows = int(match.group(1)), int(match.group(2))
    if max(cols, rows) > MAX_SQUARES:  # checked before OpenCV builds the board (a huge one takes minutes)
        fail(f"at most {MAX_SQUARES} squares a side, got {cols}x{rows}")
    square = _positive(parts[2], "SQUARE_MM", fail)
    if kind == "chessboard":
        if cols < 2 or rows < 2:
            fail("a chessboard needs at least 2x2 inner corners")
        return Board("chessboard", cols, rows, square)
    if cols < 3 or rows < 3:
        fail("a ChArUco board needs at least 3x3 squares")
    marker = _positive(parts[3], "MARKER_MM", fail)
    if marker >= square:
        fail(f"MARKER_MM ({_num(marker)}) must be smaller than SQUARE_MM ({_num(square)})")
    name = parts[4].upper()
    if not name.startswith("DICT_"):
        name = "DICT_" + name
    if not isinstance(getattr(cv2.aruco, name, None), int):
        fail(f"unknown ArUco dictionary {parts[4]!r}")
    legacy = False
    if len(parts) == 6:
        if parts[5].lower() != "legacy":
            fail(f"unknown option {parts[5]!r} (only 'legacy')")
        legacy = True
    n_markers = (cols * rows) // 2
    dictionary_size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0]
    if n_markers > dictionary_size:
        fail(f"{cols}x{rows} squares need {n_markers} markers but {name} has only {dictionary_size}")
    return Board("charuco", cols, rows, square, marker, name, legacy)


def _positive(text: str, what: str, fail) -> float:
    try:
        value = float(text)
    except ValueError:
        fail(f"{what} {text!r} is not a number")
    if not np.isfinite(value) or value <= 0:
        fail(f"{what} must be positive, got {text!r}")
    return value


def _num(value: float) -> str:
    return f"{value:g}"

"""Board detection in images, folders of images and videos.

All detections of a calibration are one :class:`Detections` object whose
``corners`` array is camera-first, ``(n_cams, n_views, n_corners, 2)``, NaN
where a corner was not seen. A "view" is one instant shared by all cameras
(images paired across folders by file name, videos by frame index).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from livebridge.calibration.boards import Board
from livebridge.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm")


@dataclass(frozen=True, eq=False)
class Detections:
    """Board corners seen by every camera in every view.

    Attributes
    ----------
    camera_names : tuple of str
    sizes : tuple of (int, int)
        Image ``(width, height)`` per camera.
    corners : ndarray, shape (n_cams, n_views, n_corners, 2)
        Pixel positions, NaN where unseen.
    view_names : tuple of str
        One label per view (file name or frame index).
    """

    camera_names: tuple[str, ...]
    sizes: tuple[tuple[int, int], ...]
    corners: np.ndarray
    view_names: tuple[str, ...]

    @property
    def n_cams(self) -> int:
        return len(self.camera_names)

    @property
    def n_views(self) -> int:
        return self.corners.shape[1]

    def seen(self) -> np.ndarray:
        """Corner visibility, bool (n_cams, n_views, n_corners)."""
        return np.isfinite(self.corners[..., 0])

    def counts(self) -> np.ndarray:
        """Corners seen per camera and view, int (n_cams, n_views)."""
        return self.seen().sum(axis=2)


@dataclass(frozen=True, eq=False)
class FoundCorners:
    """One camera's board corners detected where its frame was taken (a camera node ran :func:`detect_board`),
    in place of the image in a frame set of :func:`detect_frames`.

    Attributes
    ----------
    corners : ndarray, shape (n_corners, 2)
        Pixel positions, NaN where not found.
    size : tuple of (int, int)
        The camera's image ``(width, height)``.
    """

    corners: np.ndarray
    size: tuple[int, int]


def detect_board(board: Board, image: np.ndarray) -> np.ndarray:
    """Board corners in one image.

    Parameters
    ----------
    board : Board
    image : ndarray, shape (h, w) or (h, w, 3), uint8

    Returns
    -------
    ndarray, shape (n_corners, 2): sub-pixel corners, NaN rows for corners not found
    (a detection with fewer than ``board.min_corners`` corners is all NaN).
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    out = np.full((board.n_corners, 2), np.nan)
    if board.kind == "chessboard":
        corners = _detect_chessboard(board, gray)
        if corners is not None:
            out[:] = corners
        return out
    detector = _charuco_detector(board)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < board.min_corners:
        return out
    ids = ids.ravel()
    corners = corners.reshape(-1, 2).astype(np.float64)
    if board.cv_board.checkCharucoCornersCollinear(ids.reshape(-1, 1)):
        return out
    out[ids] = corners
    return out


def _detect_chessboard(board: Board, gray: np.ndarray) -> np.ndarray | None:
    pattern = (board.cols, board.rows)
    found, corners = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    if not found:
        found, corners = cv2.findChessboardCorners(
            gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            return None
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
        window = int(np.clip(_min_spacing(corners.reshape(-1, 2), board) / 3, 2, 11))
        corners = cv2.cornerSubPix(gray, corners, (window, window), (-1, -1), criteria)
    corners = corners.reshape(-1, 2).astype(np.float64)
    return _orient_chessboard(board, gray, corners)


def _min_spacing(corners: np.ndarray, board: Board) -> float:
    grid = corners.reshape(board.rows, board.cols, 2)
    dx = np.linalg.norm(np.diff(grid, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(grid, axis=0), axis=2)
    return float(min(dx.min(), dy.min()))


def _orient_chessboard(board: Board, gray: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Put corner 0 next to a dark square, as printed (OpenCV may return the grid turned).

    The square between corners 0, 1, COLS, COLS+1 is dark on the printed board. When the detector's order
    has it light, the grid is turned by the first turn that swaps the colours (a half turn when COLS + ROWS
    is odd, a quarter turn on a square board of odd COLS). Turns that keep the colours are left as found:
    calibration resolves them across views (:mod:`livebridge.calibration.orientation`).
    """
    swapping = [r for r in board.grid_rotations if not r.keeps_colours]
    if not swapping:
        return corners
    grid = corners.reshape(board.rows, board.cols, 2)
    first = grid[:2, :2].reshape(-1, 2).mean(axis=0)  # square (1, 1) counted from the outer corner: dark
    second = grid[:2, 1:3].reshape(-1, 2).mean(axis=0)  # its neighbour along x: light
    values = cv2.getRectSubPix(gray.astype(np.float32), (3, 3), tuple(first)).mean(), \
        cv2.getRectSubPix(gray.astype(np.float32), (3, 3), tuple(second)).mean()
    return corners[swapping[0].order].copy() if values[0] > values[1] else corners


_DETECTORS: dict[Board, object] = {}


def _charuco_detector(board: Board):
    if board not in _DETECTORS:
        charuco_parameters = cv2.aruco.CharucoParameters()
        detector_parameters = cv2.aruco.DetectorParameters()
        detector_parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        _DETECTORS[board] = cv2.aruco.CharucoDetector(board.cv_board, charuco_parameters, detector_parameters)
    return _DETECTORS[board]


# ---------------------------------------------------------------- image sets and videos


def list_images(folder: str | Path, name: str = "") -> list[Path]:
    """Image files of a camera, in natural sort order.

    ``folder`` is a directory, or a glob pattern such as ``data/left*.jpg``.
    """
    text = str(folder)
    if any(ch in text for ch in "*?["):
        base = Path(text).parent
        files = [p for p in base.glob(Path(text).name) if p.is_file()]
    else:
        base = Path(text)
        if not base.is_dir():
            raise InputError("not a folder of images (or a glob pattern such as 'dir/left*.jpg')", base,
                             f"--images {name}")
        files = [p for p in base.iterdir() if p.is_file()]
    files = [p for p in files if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")]
    if not files:
        raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) found", text, f"--images {name}")
    return sorted(files, key=_natural_key)


def _natural_key(path: Path) -> tuple:
    return tuple(int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)), path.name


def pair_images(files: Sequence[Sequence[Path]]) -> tuple[list[str], list[list[Path | None]]]:
    """Pair image files across cameras.

    Files pair by identical stem when the cameras share stems; otherwise by the last number
    in the name (``left07.jpg`` with ``right07.jpg``) when that number is unique per camera;
    otherwise by position in natural sort order (which needs equal counts).

    Returns
    -------
    view_names : list of str
    table : list (per camera) of lists (per view) of Path or None
    """
    stems = [{p.stem: p for p in cam} for cam in files]
    shared = set.intersection(*(set(s) for s in stems)) if stems else set()
    if len(files) == 1 or shared and all(len(shared) >= 0.5 * len(s) for s in stems):
        keys = sorted(set().union(*stems), key=lambda k: _natural_key(Path(k)))
        return keys, [[s.get(k) for k in keys] for s in stems]
    numbered = [{_last_number(p): p for p in cam} for cam in files]
    if all(None not in n and len(n) == len(cam) for n, cam in zip(numbered, files)):
        keys = sorted(set().union(*numbered))
        return [str(k) for k in keys], [[n.get(k) for k in keys] for n in numbered]
    counts = [len(cam) for cam in files]
    if len(set(counts)) != 1:
        raise InputError(f"cannot pair images across cameras: no shared file names or frame numbers, and the "
                         f"counts differ ({counts})", field="--images")
    return [p.stem for p in files[0]], [list(cam) for cam in files]


def _last_number(path: Path) -> int | None:
    numbers = re.findall(r"\d+", path.stem)
    return int(numbers[-1]) if numbers else None


def read_image(path: Path) -> np.ndarray:
    """Grayscale uint8 image; unreadable files raise :class:`InputError`."""
    data = np.fromfile(str(path), dtype=np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
    if image is None:
        raise InputError("not a readable image", path)
    return image


def detect_images(board: Board, cameras: dict[str, str | Path], progress: bool = True) -> Detections:
    """Detect the board in folders of images, one folder (or glob pattern) per camera.

    Parameters
    ----------
    board : Board
    cameras : dict
        Camera name -> folder or glob pattern (iteration order = camera order).
    progress : bool
        Show a tqdm progress bar.
    """
    names = list(cameras)
    files = [list_images(cameras[name], name) for name in names]
    view_names, table = pair_images(files)
    sizes: list[tuple[int, int] | None] = [None] * len(names)
    corners = np.full((len(names), len(view_names), board.n_corners, 2), np.nan)
    jobs = [(c, v, path) for c, row in enumerate(table) for v, path in enumerate(row) if path is not None]
    for c, v, path in _progress(jobs, progress, "detecting board"):
        image = read_image(path)
        size = (image.shape[1], image.shape[0])
        if sizes[c] is None:
            sizes[c] = size
        elif sizes[c] != size:
            raise InputError(f"image size {size[0]}x{size[1]} differs from this camera's other images "
                             f"({sizes[c][0]}x{sizes[c][1]})", path, f"--images {names[c]}")
        corners[c, v] = detect_board(board, image)
    return Detections(tuple(names), tuple(sizes), corners, tuple(view_names))


def detect_frames(board: Board, names: Sequence[str],
                  frames: Iterable[Sequence[np.ndarray | FoundCorners | None]],
                  progress: bool = True, total: int | None = None, every: int = 1) -> Detections:
    """Detect the board in synchronised frame sets (videos, live sources).

    Parameters
    ----------
    names : sequence of str
        Camera names.
    frames : iterable of sequences
        One image (or None when missing, or the corners already found in it: :class:`FoundCorners`) per
        camera, per instant.
    every : int
        Use every ``every``-th frame set.
    """
    sizes: list[tuple[int, int] | None] = [None] * len(names)
    rows, view_names = [], []
    for index, frame_set in enumerate(_progress(frames, progress, "detecting board", total)):
        if index % every:
            continue
        row = np.full((len(names), board.n_corners, 2), np.nan)
        for c, image in enumerate(frame_set):
            if image is None:
                continue
            if isinstance(image, FoundCorners):
                if image.corners.shape != row[c].shape:
                    raise InputError(f"{image.corners.shape[0]} board corners found, the board has "
                                     f"{board.n_corners}", field=names[c])
                sizes[c] = sizes[c] or tuple(image.size)
                row[c] = image.corners
                continue
            sizes[c] = sizes[c] or (image.shape[1], image.shape[0])
            row[c] = detect_board(board, image)
        rows.append(row)
        view_names.append(str(index))
    for name, size in zip(names, sizes):
        if size is None:
            raise InputError("no frames could be read", field=name)
    corners = np.stack(rows, axis=1) if rows else np.full((len(names), 0, board.n_corners, 2), np.nan)
    return Detections(tuple(names), tuple(sizes), corners, tuple(view_names))


def read_videos(videos: dict[str, str | Path]) -> tuple[Iterable[list[np.ndarray | None]], int]:
    """Frame sets from video files paired by frame index, and the number of frame sets."""
    captures = []
    for name, path in videos.items():
        if not Path(path).is_file():
            raise InputError("video file not found", path, f"--videos {name}")
        capture = cv2.VideoCapture(str(path))
        if not capture.isOpened():
            raise InputError("not a readable video", path, f"--videos {name}")
        captures.append(capture)
    total = max(int(c.get(cv2.CAP_PROP_FRAME_COUNT)) for c in captures)

    def frames():
        try:
            while True:
                frame_set = []
                for capture in captures:
                    ok, frame = capture.read()
                    frame_set.append(frame if ok else None)
                if all(f is None for f in frame_set):
                    return
                yield frame_set
        finally:
            for capture in captures:
                capture.release()

    return frames(), total


def _progress(items, enabled: bool, description: str, total: int | None = None):
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=description, unit="img", total=total, leave=False)


Progress = Callable[[Iterable], Iterable]

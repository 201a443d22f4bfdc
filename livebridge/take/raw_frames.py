"""Raw camera frames on disk: the format :mod:`livebridge.take.replay` plays back as cameras.

A raw-frame take is a folder with, per camera ``NAME``:

- either a folder ``NAME/`` of image files (PNG, JPEG, BMP, TIFF, PGM; played in file-name order),
  or a video ``NAME.avi`` / ``NAME.mkv`` / ``NAME.mp4`` (frames converted to grayscale);
- a timestamp file ``NAME.csv`` with a header row and one row per frame, in order: columns
  ``seq`` (int), ``t_capture`` (seconds, any monotonic clock), and optionally ``exposure_us``, ``gain``,
  ``sync_domain``, ``source_id`` (the camera's original name, e.g. ``DEVICE/CAM_B``, which the
  replayed frames carry so that a calibration matches them; default ``NAME``). Without the file,
  frames are numbered from 0 at a given ``fps``.
  Images beyond the last row (a recording cut short between an image and its row) are ignored, and so is
  a last row without its newline (cut short by a crash).

:class:`RawFrameWriter` writes this format incrementally and crash-safely (each image is written under a
temporary name and renamed; each timestamp row is flushed once its image is in place). A take directory
(:mod:`livebridge.take.directory`) keeps its raw frames in this format in its ``frames/`` folder.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.capture.frame import Frame
from livebridge.errors import InputError
from livebridge.take.directory import is_take_dir, raw_frames_folder, read_text

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")
VIDEO_SUFFIXES = (".avi", ".mkv", ".mp4")
COLUMNS = ("seq", "t_capture", "exposure_us", "gain", "sync_domain", "source_id")


@dataclass(frozen=True)
class TimestampRow:
    """One row of a camera's timestamp file (see the module docstring)."""

    seq: int
    t_capture: float
    exposure_us: float
    gain: float
    sync_domain: str
    source_id: str = ""


def read_timestamps(path: Path) -> list[TimestampRow]:
    """Rows of a camera's timestamp file, every field checked: errors name the file, the line and the column
    (unknown or missing columns, ragged rows, non-numbers, non-finite values). The order is the recording's
    (a camera's clock may step back; replay plays the rows as they are)."""
    path = Path(path)
    text = read_text(path)
    lines = text.split("\n")[:-1] if "\n" in text else [text]  # a last line without its newline: torn by a crash
    reader = csv.reader(line.rstrip("\r") for line in lines)
    header = next(reader, [])
    unknown = [c for c in header if c not in COLUMNS]
    if unknown:
        raise InputError(f"unknown column(s) {', '.join(map(repr, unknown))}; known: {', '.join(COLUMNS)}", path,
                         "line 1")
    missing = [c for c in ("seq", "t_capture") if c not in header]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}", path, "line 1")
    rows = []
    for line, fields in enumerate(reader, start=2):
        if not fields:
            continue  # a blank line
        if len(fields) != len(header):
            raise InputError(f"{len(fields)} fields, expected {len(header)}", path, f"line {line}")
        rows.append(_timestamp_row(path, line, dict(zip(header, fields)), header))
    return rows


def _timestamp_row(path: Path, line: int, values: dict[str, str], header: list[str]) -> TimestampRow:
    def number(column: str, kind: type = float, optional: bool = False):
        text = values.get(column, "")
        if optional and text == "":
            return math.nan
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or math.isinf(value) or math.isnan(value) and not optional:  # NaN: exposure unknown
            raise InputError(f"expected a finite {'integer' if kind is int else 'number'}"
                             f"{', nan or an empty field' if optional else ''}, got {text!r:.40}", path,
                             f"line {line}, column {header.index(column) + 1} ({column})")
        return value

    return TimestampRow(number("seq", int), number("t_capture"), number("exposure_us", optional=True),
                        number("gain", optional=True), values.get("sync_domain", ""), values.get("source_id", ""))


def frames_folder(folder: str | Path) -> Path:
    """The folder holding the raw frames: ``folder`` itself, or its ``frames/`` when ``folder`` is a take
    directory."""
    folder = Path(folder)
    return raw_frames_folder(folder) if is_take_dir(folder) else folder


def camera_names(folder: str | Path) -> list[str]:
    """Camera names in a raw-frame take (or a take directory's raw frames), in name order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("no such take folder", folder)
    folder = frames_folder(folder)
    names = {p.name for p in folder.iterdir() if p.is_dir()}
    names |= {p.stem for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES}
    if not names:
        raise InputError("no camera folders or videos in the take", folder)
    return sorted(names)


class RawFrameWriter:
    """Records camera frames as a raw-frame take (see the module docstring).

    Crash-safe and incremental: each image is written under a temporary name (``.NAME.part``, ignored by
    the reader) and renamed, then its timestamp row is written and flushed, so a take cut short by a crash
    replays up to its last complete frame.

    Parameters
    ----------
    folder : str or Path
        Created if missing.
    image_format : str
        ``.png`` (lossless, default) or another OpenCV image suffix.
    """

    def __init__(self, folder, image_format: str = ".png"):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.image_format = image_format
        self._streams: dict[str, tuple] = {}
        self._counts: dict[str, int] = {}

    @staticmethod
    def camera_name(source_id: str) -> str:
        """The file-system name of a camera (``/`` and other unsafe characters become ``_``)."""
        return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(source_id)).lstrip(".") or "camera"

    def write(self, frame: Frame) -> None:
        import cv2

        name = self.camera_name(frame.source_id)
        if name not in self._streams:
            (self.folder / name).mkdir(exist_ok=True)
            stream = (self.folder / f"{name}.csv").open("w", newline="", buffering=1)
            writer = csv.writer(stream, lineterminator="\n")
            writer.writerow(COLUMNS)
            self._streams[name] = (stream, writer)
            self._counts[name] = 0
        stream, writer = self._streams[name]
        index = self._counts[name]
        ok, data = cv2.imencode(self.image_format, np.asarray(frame.image))
        if not ok:
            raise InputError(f"OpenCV cannot encode {self.image_format} images", self.folder)
        target = self.folder / name / f"{index:06d}{self.image_format}"
        partial = target.with_name(f".{target.name}.part")
        partial.write_bytes(data.tobytes())
        os.replace(partial, target)
        writer.writerow([frame.seq, repr(frame.t_capture), repr(frame.exposure_us), repr(frame.gain),
                         frame.sync_domain, frame.source_id])  # line-buffered: on disk once written
        self._counts[name] = index + 1

    @property
    def counts(self) -> dict[str, int]:
        """Frames written per camera (file-system names)."""
        return dict(self._counts)

    def close(self) -> None:
        for stream, _ in self._streams.values():
            stream.close()
        self._streams.clear()

    def __enter__(self) -> RawFrameWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

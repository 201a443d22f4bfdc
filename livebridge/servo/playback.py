"""Contraction files played on the head: read, clean, and pace through the live path's safety stage.

A contraction file is CSV text with a header row: a time column (``t``, ``time`` or ``time_s``, seconds)
and one column per muscle, as ``livebridge solve`` writes it and as the recorder's ``contractions.csv`` in
a take directory (whose ``frame``, ``seq`` and ``error_*`` columns are bookkeeping, not muscles). Comma,
semicolon or tab separated.

What real files contain, and what playback does with it (:func:`read_contractions`):

- an empty, ``NA`` or ``NaN`` cell (or ``inf``): the muscle holds its last value (neutral, 0, before its
  first value);
- a value outside [0, 1]: clipped (the safety stage limits the servos again);
- a muscle the file lacks: neutral (0) throughout;
- a column that is no muscle: an error naming it, unless ``ignore_extra``;
- time not after the previous row's (a time going backwards or repeating): the row is skipped and
  counted, so the head never gets a burst of stale frames;
- a gap in time: the last row is held through it (:func:`play` sends at the rig's frame rate, so the
  safety stage sees regular steps and its watchdog does not trip).

Errors name the file, line and column.
"""

from __future__ import annotations

import csv
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from livebridge.errors import InputError

TIME_COLUMNS = ("t", "time", "time_s")
BOOKKEEPING_COLUMNS = ("frame", "seq")  # the recorder's frame counter and frame-set number
DIAGNOSTIC_PREFIXES = ("error_", "rms_")  # per-frame solve errors written beside the contractions
MISSING_CELLS = ("", "na", "nan", "n/a", "null")
DELIMITERS = (",", ";", "\t")

CLOCK = time.monotonic
"""The monotonic clock playback is paced by (tests put a fake clock here)."""
SLEEP = time.sleep
"""How playback waits for the next frame (tests put the fake clock's sleep here)."""


@dataclass(frozen=True, eq=False)
class ContractionTrack:
    """A contraction file read and cleaned.

    Attributes
    ----------
    path : Path
    t : ndarray, shape (n_rows,)
        Seconds from the first kept row (0), strictly increasing.
    values : ndarray, shape (n_rows, n_muscles)
        Contractions in ``muscle_names`` order, finite, inside [0, 1].
    muscle_names : tuple of str
    notes : tuple of str
        What cleaning did (held cells, clipped values, skipped rows, missing muscles), for the user.
    """

    path: Path
    t: np.ndarray
    values: np.ndarray
    muscle_names: tuple[str, ...]
    notes: tuple[str, ...] = field(default=())

    @property
    def duration(self) -> float:
        """Seconds the track lasts: to the last row plus one typical row interval (so the last row plays)."""
        step = float(np.median(np.diff(self.t))) if len(self.t) > 1 else 0.0
        return float(self.t[-1]) + step

    def at(self, seconds: float) -> np.ndarray:
        """The row in force ``seconds`` after the start (the last row at or before it), shape (n_muscles,)."""
        i = int(np.searchsorted(self.t, seconds, side="right")) - 1
        return self.values[max(i, 0)]


def _delimiter(header_line: str) -> str:
    counts = {d: header_line.count(d) for d in DELIMITERS}
    best = max(counts, key=counts.get)
    return best if counts[best] else ","


def _columns(header: list[str], muscle_names, path: Path, ignore_extra: bool) -> tuple[int, dict[int, int]]:
    """Index of the time column and {file column: muscle index} from the header row."""
    names = [name.strip() for name in header]
    times = [k for k, name in enumerate(names) if name.lower() in TIME_COLUMNS]
    if not times:
        raise InputError(f"no time column (one of {', '.join(TIME_COLUMNS)}); columns: {', '.join(names)[:200]}",
                         path, "line 1")
    index = {name: i for i, name in enumerate(muscle_names)}
    muscles, extra, seen = {}, [], set()
    for k, name in enumerate(names):
        if k == times[0] or name.lower() in BOOKKEEPING_COLUMNS or name.lower().startswith(DIAGNOSTIC_PREFIXES):
            continue
        if name in seen:
            raise InputError(f"column {name!r} repeats", path, f"line 1, column {k + 1}")
        seen.add(name)
        if name in index:
            muscles[k] = index[name]
        else:
            extra.append(name)
    if extra and not ignore_extra:
        raise InputError(f"unknown muscle column{'s' if len(extra) > 1 else ''} {', '.join(map(repr, extra))} "
                         f"(muscles: {', '.join(muscle_names)}; --ignore-extra to leave them out)", path, "line 1")
    if not muscles:
        raise InputError("no muscle columns", path, "line 1")
    return times[0], muscles


def _number(cell: str, path: Path, line: int, column: int, name: str) -> float:
    text = cell.strip()
    if text.lower() in MISSING_CELLS:
        return math.nan
    try:
        return float(text)
    except ValueError:
        raise InputError(f"expected a number or an empty cell, got {text[:40]!r}", path,
                         f"line {line}, column {column} ({name})") from None


def _rows(path: Path):
    """(delimiter, header, [(line number, cells)], torn last line or None) of a CSV file."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as error:
        raise InputError(f"not UTF-8 text (byte offset {error.start}): a contraction file is CSV text", path) \
            from None
    lines = text.splitlines()
    if not lines or not lines[0].strip():
        raise InputError("empty file (expected a header row)", path, "line 1")
    delimiter = _delimiter(lines[0])
    rows = list(enumerate(csv.reader(lines, delimiter=delimiter), start=1))
    header = rows[0][1]
    body = [(n, cells) for n, cells in rows[1:] if any(c.strip() for c in cells)]
    torn = None
    if body and len(body[-1][1]) < len(header) and not text.endswith(("\n", "\r")):
        torn = body.pop()[0]  # a file cut short mid-line (a recorder that crashed): its last line is dropped
    return header, body, torn


def read_contractions(path, muscle_names, ignore_extra: bool = False) -> ContractionTrack:
    """Read and clean a contraction file (see the module docstring).

    Parameters
    ----------
    path : str or Path
    muscle_names : sequence of str
        The muscles to play, in the order of the returned values.
    ignore_extra : bool
        Leave out columns that are not muscles instead of refusing the file.
    """
    path = Path(path)
    muscle_names = tuple(muscle_names)
    header, body, torn = _rows(path)
    time_column, muscles = _columns(header, muscle_names, path, ignore_extra)
    names = [name.strip() for name in header]
    times, table, skipped, notes = [], [], [], []
    for line, cells in body:
        if len(cells) != len(header):
            raise InputError(f"{len(cells)} fields, the header has {len(header)}", path, f"line {line}")
        t = _number(cells[time_column], path, line, time_column + 1, names[time_column])
        if not math.isfinite(t):
            raise InputError(f"expected a finite time, got {cells[time_column].strip()[:40]!r}", path,
                             f"line {line}, column {time_column + 1} ({names[time_column]})")
        if times and t <= times[-1]:
            skipped.append(line)
            continue
        row = np.full(len(muscle_names), np.nan)
        for k, m in muscles.items():
            row[m] = _number(cells[k], path, line, k + 1, names[k])
        times.append(t)
        table.append(row)
    if not times:
        raise InputError("no rows of contractions", path, "line 2")
    values = np.array(table)
    if torn is not None:
        notes.append(f"line {torn} is cut short (the file ends mid-line): left out")
    if skipped:
        notes.append(f"{len(skipped)} row{'s' if len(skipped) > 1 else ''} whose time does not go forward skipped "
                     f"(first: line {skipped[0]})")
    notes += _clean(values, muscle_names, set(muscles.values()))
    t = np.array(times)
    return ContractionTrack(path, t - t[0], values, muscle_names, tuple(notes))


def _clean(values: np.ndarray, muscle_names, present: set[int]) -> list[str]:
    """Hold the last finite value through missing cells (0 before the first), clip to [0, 1]; in place."""
    notes = []
    absent = [name for i, name in enumerate(muscle_names) if i not in present]
    if absent:
        notes.append(f"no column for {', '.join(absent)}: neutral (0) throughout")
    missing = ~np.isfinite(values)
    held = int(missing[:, sorted(present)].sum())
    index = np.where(missing, 0, np.arange(len(values))[:, None])
    np.maximum.accumulate(index, axis=0, out=index)
    filled = np.take_along_axis(values, index, axis=0)
    filled[~np.isfinite(filled)] = 0.0  # before a muscle's first value
    clipped = int(np.sum((filled < 0) | (filled > 1)))
    values[:] = np.clip(filled, 0.0, 1.0)
    if held:
        notes.append(f"{held} empty or non-finite cell{'s' if held > 1 else ''}: last value held")
    if clipped:
        notes.append(f"{clipped} value{'s' if clipped > 1 else ''} outside [0, 1] clipped")
    return notes


@dataclass
class PlaybackReport:
    """What :func:`play` did: frames sent, passes through the file, whether it was interrupted."""

    frames: int = 0
    passes: int = 0
    interrupted: bool = False


def play(track: ContractionTrack, output, speed: float = 1.0, loop: bool = False, render=None,
         clock=None, sleep=None, log=None) -> PlaybackReport:
    """Drive an activated-and-configured :class:`~livebridge.servo.output.ServoOutput` from ``track``.

    Sends at the rig's frame rate, each frame the row in force at the file time
    ``(now - start) * speed``; at the end (or on Ctrl-C) eases to neutral through the safety stage's
    watchdog. The caller configures the output before and closes it after (torque off).

    Parameters
    ----------
    track : ContractionTrack
    output : ServoOutput
        Configured, not yet activated (:func:`play` activates it at its start time).
    speed : float
        File seconds per wall second (> 0).
    loop : bool
        Start again from the first row at the end, until Ctrl-C.
    render : callable, optional
        Called with ``(frame number, time, contractions (n_muscles,), raw targets (n_servos,))`` per frame.
    clock, sleep : callable, optional
        The monotonic clock and its sleep (default :data:`CLOCK`, :data:`SLEEP`).
    """
    clock = clock or CLOCK
    sleep = sleep or SLEEP
    log = log or (lambda message: None)
    if not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"speed must be finite and > 0, got {speed}")
    report = PlaybackReport()
    period = output.frame_period
    duration = max(track.duration, period)  # a one-row file is one frame long
    _warm_up(output.mapper, len(track.muscle_names))
    start = clock()
    output.activate(start)
    try:
        while True:
            now = clock()
            elapsed = (now - start) * speed
            if not loop and elapsed >= duration:
                break
            report.passes = int(elapsed // duration) + 1
            x = track.at(elapsed % duration)
            raw = output.send(x, now)
            if render is not None:
                render(report.frames, now, x, raw)
            report.frames += 1
            _wait_until(start + report.frames * period, clock, sleep)
    except KeyboardInterrupt:
        report.interrupted = True
        log("interrupted: easing to neutral")
    ease_to_neutral(output, clock, sleep)
    if report.interrupted:
        raise KeyboardInterrupt
    return report


def _warm_up(mapper, n_muscles: int) -> None:
    """One step of the safety stage on nothing, so its kernel is compiled before the clock starts (else the
    first frame comes late and the start of the file is skipped to keep time)."""
    mapper.step(mapper.start(mapper.neutral, 0.0), np.zeros(n_muscles), mapper.soft_start_s + 1.0)


def _wait_until(deadline: float, clock, sleep) -> None:
    remaining = deadline - clock()
    if remaining > 0:
        sleep(remaining)


def ease_to_neutral(output, clock, sleep) -> None:
    """Send no contractions until the safety stage's watchdog has eased every servo to neutral (or timed out).

    Unlike :meth:`ServoOutput.ease_to_neutral`, paced by the given clock and sleep.
    """
    if output.state is None or output.state.estopped:
        return
    rig = output.rig
    deadline = clock() + rig.watchdog_s + rig.ease_s + 1.0
    while clock() < deadline:
        output.send(None, clock())
        if np.all(np.abs(output.state.target - output.mapper.neutral) < 0.5):
            break
        _wait_until(clock() + output.frame_period, clock, sleep)

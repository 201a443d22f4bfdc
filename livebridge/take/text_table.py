"""Shared pieces of the text marker-file readers (TRC, CSV): lines, numbers and times, every error naming
the file, the line and the column."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.take.directory import read_text

MISSING = frozenset({"", "na", "nan", "n/a"})
"""Fields that mean "not seen" (compared lower-case, blanks trimmed)."""


def text_lines(path: Path) -> list[str]:
    """The lines of the UTF-8 text file ``path`` (a byte-order mark dropped, any newline convention)."""
    return read_text(path).removeprefix("\ufeff").splitlines()


def where(line: int, column: int | None = None, name: str | None = None) -> str:
    """``"line 3, column 5 (a_x)"``: the field of an error."""
    place = f"line {line}"
    if column is not None:
        place += f", column {column}"
    return place + (f" ({name})" if name else "")


def number(field: str, path: Path, line: int, column: int, name: str | None = None,
           missing_ok: bool = True, decimal_comma: bool = False) -> float:
    """The finite number in ``field``; NaN for a missing value (:data:`MISSING`) when ``missing_ok``."""
    text = field.strip()
    if text.lower() in MISSING:
        if missing_ok:
            return math.nan
        raise InputError("expected a number, the field is empty", path, where(line, column, name))
    try:
        value = float(text.replace(",", ".") if decimal_comma else text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise InputError(f"expected a number{' or an empty field' if missing_ok else ''}, got {text!r:.40}",
                         path, where(line, column, name))
    return value


def increasing_times(t: np.ndarray, lines: list[int], path: Path, column: int, name: str) -> np.ndarray:
    """``t - t[0]`` after checking that ``t`` (one value per data line ``lines``) strictly increases."""
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise InputError(f"{name} does not increase ({t[k - 1]:g} on line {lines[k - 1]}, then {t[k]:g})", path,
                         where(lines[k], column, name))
    return t - t[0] if len(t) else t


def whole_points(xyz: np.ndarray) -> np.ndarray:
    """``xyz`` (..., 3) with a point that misses any coordinate NaN in all three (a marker is seen or not)."""
    return np.where(np.all(np.isfinite(xyz), axis=-1)[..., None], xyz, np.nan)


def repeated(names, path: Path, line: int, columns) -> None:
    """Refuse a name that appears twice (``columns``: the column of each name, for the error)."""
    seen: dict[str, int] = {}
    for name, column in zip(names, columns):
        if name in seen:
            raise InputError(f"marker name {name!r} repeats (columns {seen[name]} and {column})", path,
                             where(line, column))
        seen[name] = column


def format_number(value: float) -> str:
    """The shortest text that reads back as exactly ``value``; empty for NaN."""
    return "" if not math.isfinite(value) else repr(float(value))


def number_table(cells: list[list[str]], lines: list[int], columns: list[int], names: list[str], path: Path,
                 missing_ok: bool = True, decimal_comma: bool = False) -> np.ndarray:
    """The numbers in a table of text fields at once (a long take is millions of fields).

    Parameters
    ----------
    cells : list of list of str, shape (n_rows, n_columns)
    lines : list of int, length n_rows
        The file's line number of each row (for errors).
    columns : list of int, length n_columns
        The file's 1-based column number of each field (for errors).
    names : list of str, length n_columns
        The column names (for errors).

    Returns
    -------
    ndarray, shape (n_rows, n_columns)
        NaN for missing values (:data:`MISSING`) when ``missing_ok``; anything else not a finite number
        raises :class:`InputError` naming the first such field's line and column.
    """
    text = np.char.strip(np.array(cells, dtype=str).reshape(len(cells), len(columns)))
    if decimal_comma:
        text = np.char.replace(text, ",", ".")
    missing = np.isin(np.char.lower(text), list(MISSING))
    try:
        values = np.where(missing, "nan", text).astype(np.float64)
    except ValueError:  # some field is not a number: field by field, so the error names the first
        return np.array([[number(cell, path, line, column, name, missing_ok, decimal_comma)
                          for cell, column, name in zip(row, columns, names)] for row, line in zip(cells, lines)],
                        dtype=np.float64).reshape(len(cells), len(columns))
    bad = ~np.isfinite(values) & ~(missing if missing_ok else np.zeros_like(missing))
    for row, column in zip(*np.nonzero(bad)):  # inf, or a missing value where none may be: raises
        number(cells[row][column], path, lines[row], columns[column], names[column], missing_ok, decimal_comma)
    return values

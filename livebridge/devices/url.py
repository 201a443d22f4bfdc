"""The one strict parser of device URLs (cameras and servo buses): ``scheme://netloc/path?key=value&...``.

Every opener declares the query parameters it knows (:meth:`DeviceURL.check_known`); a parameter it does
not know or a parameter given twice is an :class:`~livebridge.errors.InputError` naming the parameter and
the URL, so a typo is never silently ignored.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

from livebridge.errors import InputError

_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")


@dataclass(frozen=True)
class DeviceURL:
    """A parsed device URL.

    Attributes
    ----------
    url : str
        The URL as given (errors quote it).
    scheme : str
        Lower case.
    netloc, path : str
    query : dict of str to str
        Each parameter once.
    """

    url: str
    scheme: str
    netloc: str
    path: str
    query: dict[str, str]

    @classmethod
    def parse(cls, url: str) -> DeviceURL:
        """Split ``url``; a parameter given twice raises :class:`InputError` naming it."""
        parts = urlsplit(url)
        if not parts.scheme:
            raise InputError("a device URL needs a scheme (v4l2://, depthai://, replay://, sim://, dynamixel://, "
                             "maestro://, ssc32://, simdynamixel://, ...)", url)
        query = {}
        for key, values in parse_qs(parts.query, keep_blank_values=True).items():
            if len(values) > 1:
                raise InputError(f"parameter {key!r} given {len(values)} times", url, key)
            query[key] = values[0]
        return cls(url, parts.scheme.lower(), parts.netloc, parts.path, query)

    def take(self, key: str, kind: type, default=None, within: tuple[float, float] | None = None):
        """The value of parameter ``key`` converted to ``kind`` (bool accepts 0/1/true/false/yes/no/on/off);
        ``default`` when the URL does not give it. ``within=(low, high)``: a number outside it (or NaN) is an
        :class:`InputError` naming the parameter."""
        value = self._convert(key, kind, default)
        if within is not None and value is not None and not within[0] <= value <= within[1]:  # also refuses NaN
            raise InputError(f"parameter {key!r} must be in {within[0]:g}..{within[1]:g}, got {value}", self.url, key)
        return value

    def _convert(self, key: str, kind: type, default):
        if key not in self.query:
            return default
        raw = self.query[key]
        try:
            if kind is bool:
                lowered = raw.lower()
                if lowered in _TRUE:
                    return True
                if lowered in _FALSE:
                    return False
                raise ValueError(raw)
            return kind(raw)
        except ValueError:
            raise InputError(f"parameter {key!r}: expected {kind.__name__}, got {raw!r}", self.url, key) from None

    def check_known(self, known: Iterable[str]) -> None:
        """Raise :class:`InputError` naming the first parameter the opener does not know."""
        known = set(known)
        unknown = sorted(set(self.query) - known)
        if unknown:
            raise InputError(f"unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}",
                             self.url, unknown[0])


def parse_ranges(text: str, first: int, last: int) -> list[int]:
    """``"1-4,7"`` -> ``[1, 2, 3, 4, 7]``: servo IDs or channels, each in ``first..last``, none twice.

    Bounds are checked before a range is expanded, so ``1-999999999`` is refused at once instead of
    building a list of a billion numbers.

    Raises
    ------
    InputError
        Saying which part is wrong (no path or field: the caller names the URL parameter or option).
    """
    numbers: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        low_text, dash, high_text = part.partition("-")
        try:
            low = int(low_text)
            high = int(high_text) if dash else low
        except ValueError:
            raise InputError(f"{part!r} is not a number or a range like 1-20") from None
        if not first <= low <= high <= last:
            raise InputError(f"{part!r}: numbers run {first}..{last}, ranges upwards")
        numbers.extend(range(low, high + 1))
    if not numbers:
        raise InputError(f"no number in {text!r}")
    if len(set(numbers)) != len(numbers):
        raise InputError(f"a number is given twice in {text!r}")
    return numbers

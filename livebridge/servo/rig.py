"""The rig file: which servos exist, on which bus, driven by which muscles.

A TOML file::

    frame_rate = 50.0                     # targets per second (sets the Dynamixel profile time)

    [safety]
    watchdog_s = 0.5                      # no contractions this long -> ease to neutral
    soft_start_s = 1.5                    # speed ramps up from 0 when torque comes on
    ease_s = 2.0                          # a full-range move to neutral under the watchdog takes this long
    estop = "stop"                        # Maestro/SSC-32: "stop" pulses or go "home" (Dynamixel: torque off)

    [buses.head]
    url = "dynamixel:///dev/ttyUSB0?baud=1000000"

    [servos.jaw]
    bus = "head"
    id = 3                                # Dynamixel ID; Maestro / SSC-32 use `channel = 3`
    model = "XL330-M288"                  # optional; checked against the servo's model number
    muscles = { jaw = 1.0, orbicularis_oris = -0.3 }   # weights, negative allowed
    curve = "gamma"                       # linear | gamma | piecewise
    gamma = 0.8                           # for gamma; piecewise takes points = [[u, y], ...]
    neutral = 2048                        # raw units: Dynamixel ticks, Maestro/SSC-32 microseconds
    min = 1800                            # reached at drive -1
    max = 2600                            # reached at drive +1 (max < min for an inverted servo)
    slew = 3000                           # raw units per second
    filter = { kind = "one_euro", min_cutoff = 2.0, beta = 0.5 }   # or { kind = "exponential", tau = 0.03 }

Unknown keys and tables (a misspelt ``slwe`` would otherwise leave the default
slew in place), values of the wrong type, non-finite numbers, negative or
overlong durations, unknown muscle names, two servos on one bus address, an
``id`` on a bus that addresses by ``channel`` (or the reverse), limits outside
the device's range and a neutral outside [min, max] raise :class:`InputError`
naming the file and the dotted field. :func:`set_servo_limits` edits a rig file
keeping its comments and layout, and keeps the previous file beside it.
"""

from __future__ import annotations

import difflib
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomlkit
import tomlkit.exceptions

from livebridge.atomic import write_bytes_atomically
from livebridge.devices.registry import bus_facts
from livebridge.errors import InputError
from livebridge.servo.bus import BusFacts
from livebridge.servo.mapping import _CURVE_KINDS as CURVE_KINDS
from livebridge.servo.mapping import Curve, Mapping
from livebridge.servo.safety import Filter, SafetyMapper
from livebridge.tomlio import save_toml

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


def default_muscle_names() -> tuple[str, ...]:
    from livebridge.face.basis import CHOE_KO_MUSCLES

    return tuple(m.name for m in CHOE_KO_MUSCLES)


@dataclass(frozen=True)
class BusSpec:
    """One bus of the rig: its URL and what its driver declares about the device family."""

    name: str
    url: str
    facts: BusFacts


@dataclass(frozen=True)
class ServoSpec:
    """One servo of the rig (raw units of its bus)."""

    name: str
    bus: str
    address: int
    muscles: tuple[tuple[str, float], ...]
    neutral: float
    minimum: float
    maximum: float
    slew: float
    curve: Curve = Curve()
    filter: Filter = Filter()
    model: str | None = None

    @property
    def low(self) -> float:
        return min(self.minimum, self.maximum)

    @property
    def high(self) -> float:
        return max(self.minimum, self.maximum)


@dataclass(frozen=True)
class Rig:
    """A whole rig: buses, servos and safety settings."""

    buses: dict[str, BusSpec]
    servos: tuple[ServoSpec, ...]
    frame_rate: float = 50.0
    watchdog_s: float = 0.5
    soft_start_s: float = 1.5
    ease_s: float = 2.0
    estop: str = "stop"
    path: str | None = field(default=None, compare=False)

    def servo(self, name: str) -> ServoSpec:
        for servo in self.servos:
            if servo.name == name:
                return servo
        raise KeyError(name)

    def mapping(self, muscle_names) -> Mapping:
        """The :class:`Mapping` over ``muscle_names`` (the order of the contraction vectors)."""
        index = {name: i for i, name in enumerate(muscle_names)}
        weights = np.zeros((len(self.servos), len(index)))
        for s, servo in enumerate(self.servos):
            for muscle, weight in servo.muscles:
                if muscle not in index:
                    raise InputError(f"muscle {muscle!r} is not in the basis ({', '.join(index)})", self.path,
                                     f"servos.{servo.name}.muscles")
                weights[s, index[muscle]] = weight
        return Mapping(weights, tuple(s.curve for s in self.servos),
                       np.array([s.neutral for s in self.servos], dtype=float),
                       np.array([s.minimum for s in self.servos], dtype=float),
                       np.array([s.maximum for s in self.servos], dtype=float))

    def safety(self, muscle_names) -> SafetyMapper:
        return SafetyMapper(self.mapping(muscle_names), [s.slew for s in self.servos],
                            [s.filter for s in self.servos], watchdog_s=self.watchdog_s,
                            soft_start_s=self.soft_start_s, ease_s=self.ease_s)

    def to_dict(self) -> dict[str, Any]:
        servos = {}
        for s in self.servos:
            key = self.buses[s.bus].facts.address_key
            entry: dict[str, Any] = {"bus": s.bus, key: s.address, "muscles": dict(s.muscles),
                                     "neutral": s.neutral, "min": s.minimum, "max": s.maximum, "slew": s.slew}
            if s.model:
                entry["model"] = s.model
            entry["curve"] = s.curve.kind
            if s.curve.kind == "gamma":
                entry["gamma"] = s.curve.gamma
            if s.curve.kind == "piecewise":
                entry["points"] = [list(p) for p in s.curve.points]
            if s.filter.kind == "exponential":
                entry["filter"] = {"kind": "exponential", "tau": s.filter.tau}
            elif s.filter.kind == "one_euro":
                entry["filter"] = {"kind": "one_euro", "min_cutoff": s.filter.min_cutoff, "beta": s.filter.beta,
                                   "d_cutoff": s.filter.d_cutoff}
            servos[s.name] = entry
        return {"frame_rate": self.frame_rate,
                "safety": {"watchdog_s": self.watchdog_s, "soft_start_s": self.soft_start_s, "ease_s": self.ease_s,
                           "estop": self.estop},
                "buses": {b.name: {"url": b.url} for b in self.buses.values()},
                "servos": servos}

    def save(self, path: str | Path) -> None:
        save_toml(path, self.to_dict())


def load_rig(path: str | Path, muscle_names=None) -> Rig:
    """Read and validate a rig file (see the module docstring)."""
    text = _decode(_read_bytes(Path(path)), path)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise InputError(f"not valid TOML ({error})", path) from None
    return rig_from_dict(data, path, muscle_names)


_REQUIRED = object()
_TOP_KEYS = ("frame_rate", "safety", "buses", "servos")
_SAFETY_KEYS = ("watchdog_s", "soft_start_s", "ease_s", "estop")
_BUS_KEYS = ("url",)
_SERVO_KEYS = ("bus", "id", "channel", "model", "muscles", "curve", "gamma", "points", "neutral", "min", "max",
               "slew", "filter")
_CURVE_KEYS = ("kind", "gamma", "points")
_FILTER_KEYS = {"none": ("kind",), "exponential": ("kind", "tau"),
                "one_euro": ("kind", "min_cutoff", "beta", "d_cutoff")}
MAX_DURATION_S = 3600.0
"""Longest watchdog, soft start or ease time a rig may ask for, seconds."""
FRAME_RATE_RANGE = (1.0, 1000.0)
"""Targets per second a rig may ask for (a Dynamixel profile time is whole milliseconds)."""


class _Table:
    """One table of the rig file: typed access whose errors name the file and the dotted field.

    ``known``: the keys the table may have (None: any key, e.g. the muscle weights); any other key is an
    error naming the table and the key.
    """

    def __init__(self, data: Any, path: str, prefix: str, known: tuple[str, ...] | None):
        if not isinstance(data, dict):
            raise InputError(f"expected a table, got {_describe(data)}", path, prefix or None)
        self.data, self.path, self.prefix = data, path, prefix
        for key in data:
            if known is not None and key not in known:
                raise InputError(_unknown_key(key, prefix, known), path, self.field(key))

    def field(self, key: str) -> str:
        return f"{self.prefix}.{key}" if self.prefix else key

    def __contains__(self, key: str) -> bool:
        return key in self.data

    def get(self, key: str, kind: type | tuple[type, ...], default: Any = _REQUIRED) -> Any:
        if key not in self.data:
            if default is _REQUIRED:
                raise InputError("missing", self.path, self.field(key))
            return default
        value = self.data[key]
        kinds = kind if isinstance(kind, tuple) else (kind,)
        if isinstance(value, bool) and bool not in kinds or not isinstance(value, kinds):
            wanted = "a number" if float in kinds else " or ".join(_TOML_NAMES[k] for k in kinds)
            raise InputError(f"expected {wanted}, got {_describe(value)}", self.path, self.field(key))
        return value

    def number(self, key: str, default: Any = _REQUIRED, low: float = -math.inf, high: float = math.inf,
               low_open: bool = False) -> float:
        """A finite number in ``[low, high]`` (``(low, high]`` with ``low_open``)."""
        value = self.get(key, (int, float), default)
        return _in_range(value, low, high, low_open, self.path, self.field(key))

    def table(self, key: str, known: tuple[str, ...] | None, default: Any = _REQUIRED) -> _Table:
        return _Table(self.get(key, dict, default), self.path, self.field(key), known)


_TOML_NAMES = {dict: "a table", list: "an array", str: "a string", int: "an integer", float: "a number",
               bool: "true or false"}


def _describe(value: Any) -> str:
    """A value as the error names it: its TOML kind and a short excerpt."""
    kind = next((name for k, name in reversed(_TOML_NAMES.items()) if isinstance(value, k)), type(value).__name__)
    text = repr(value)
    return f"{kind} {text if len(text) <= 40 else text[:37] + '...'}"


def _unknown_key(key: str, prefix: str, known: tuple[str, ...]) -> str:
    where = f"in table [{prefix}]" if prefix else "at the top level"
    close = difflib.get_close_matches(key, known, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"unknown key {key!r} {where} (known: {', '.join(known)}){hint}"


def _in_range(value: Any, low: float, high: float, low_open: bool, path: str, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"expected a number, got {_describe(value)}", path, field)
    value = float(value)
    too_low = value <= low if low_open else value < low
    if not math.isfinite(value) or too_low or value > high:
        bounds = f"{'>' if low_open else '>='} {low:g}" if math.isinf(high) else \
            f"in {'(' if low_open else '['}{low:g}, {high:g}]"
        raise InputError(f"must be a finite number {bounds}, got {value}", path, field)
    return value


def rig_from_dict(data: dict[str, Any], path: str | Path | None = None, muscle_names=None) -> Rig:
    """Validate a parsed rig file; ``muscle_names`` defaults to the Choe-Ko 16.

    Every key must be one the rig file knows (a misspelt key would otherwise silently leave a default in
    place); every error is an :class:`InputError` naming the file and the dotted field.
    """
    path = str(path) if path is not None else "<rig>"
    known = tuple(muscle_names) if muscle_names is not None else default_muscle_names()
    top = _Table(data, path, "", _TOP_KEYS)
    frame_rate = top.number("frame_rate", 50.0, *FRAME_RATE_RANGE)
    safety = top.table("safety", _SAFETY_KEYS, {})
    estop = safety.get("estop", str, "stop")
    if estop not in ("stop", "home"):
        raise InputError(f"estop must be 'stop' or 'home', got {estop!r}", path, "safety.estop")
    buses = _buses(top.table("buses", None), path)
    servos_table = top.table("servos", None)
    servos = []
    used: dict[tuple[str, int], str] = {}
    for name in servos_table.data:
        servo = _servo(servos_table.table(name, _SERVO_KEYS), name, buses, known)
        key = buses[servo.bus].facts.address_key
        if (servo.bus, servo.address) in used:
            raise InputError(f"servo {name!r} and servo {used[servo.bus, servo.address]!r} both use {key} "
                             f"{servo.address} on bus {servo.bus!r}", path, f"servos.{name}.{key}")
        used[servo.bus, servo.address] = name
        servos.append(servo)
    return Rig(buses, tuple(servos), frame_rate,
               watchdog_s=safety.number("watchdog_s", 0.5, 0.0, MAX_DURATION_S, low_open=True),
               soft_start_s=safety.number("soft_start_s", 1.5, 0.0, MAX_DURATION_S),
               ease_s=safety.number("ease_s", 2.0, 0.0, MAX_DURATION_S, low_open=True), estop=estop, path=path)


def _buses(table: _Table, path: str) -> dict[str, BusSpec]:
    buses = {}
    for name in table.data:
        entry = table.table(name, _BUS_KEYS)
        url = entry.get("url", str)
        try:
            facts = bus_facts(url)
        except InputError as error:
            raise InputError(error.message, path, entry.field("url")) from None
        buses[name] = BusSpec(name, url, facts)
    return buses


def _servo(entry: _Table, name: str, buses: dict[str, BusSpec], known_muscles: tuple[str, ...]) -> ServoSpec:
    path = entry.path
    bus = entry.get("bus", str)
    if bus not in buses:
        raise InputError(f"servo {name!r}: unknown bus {bus!r} (known: {', '.join(buses)})", path,
                         entry.field("bus"))
    facts = buses[bus].facts
    key = facts.address_key
    other = "channel" if key == "id" else "id"
    if other in entry:
        raise InputError(f"servo {name!r}: a {facts.kind} bus addresses servos by {key!r}, not {other!r}", path,
                         entry.field(other))
    address = entry.get(key, int)
    lo, hi = facts.address_range
    if not lo <= address <= hi:
        raise InputError(f"servo {name!r}: {key} {address} outside {lo}..{hi} for a {facts.kind} bus", path,
                         entry.field(key))
    muscles = _muscles(entry.table("muscles", None), name, known_muscles)
    neutral, minimum, maximum = (entry.number(k) for k in ("neutral", "min", "max"))
    low, high = min(minimum, maximum), max(minimum, maximum)
    dev_lo, dev_hi = facts.raw_range
    if low < dev_lo or high > dev_hi:
        raise InputError(f"servo {name!r}: limits {minimum:g}..{maximum:g} outside the {facts.kind} range "
                         f"{dev_lo:g}..{dev_hi:g}", path, entry.prefix)
    if low == high:
        raise InputError(f"servo {name!r}: min and max are equal", path, entry.prefix)
    if not low <= neutral <= high:
        raise InputError(f"servo {name!r}: neutral {neutral:g} outside {low:g}..{high:g}", path,
                         entry.field("neutral"))
    slew = entry.number("slew", (high - low) * 2.0, 0.0, low_open=True)
    model = entry.get("model", str, None)
    return ServoSpec(name, bus, address, muscles, neutral, minimum, maximum, slew, _curve(entry, name),
                     _filter(entry, name), model)


def _muscles(table: _Table, servo: str, known: tuple[str, ...]) -> tuple[tuple[str, float], ...]:
    if not table.data:
        raise InputError(f"servo {servo!r}: no muscles drive it", table.path, table.prefix)
    for muscle in table.data:
        if muscle not in known:
            raise InputError(f"servo {servo!r}: unknown muscle {muscle!r} (known: {', '.join(known)})", table.path,
                             table.field(muscle))
    return tuple((muscle, table.number(muscle)) for muscle in table.data)


def _curve(entry: _Table, servo: str) -> Curve:
    """``curve = "gamma"`` with ``gamma``/``points`` beside it, or ``curve = { kind = ..., ... }``."""
    if isinstance(entry.data.get("curve"), dict):
        for key in ("gamma", "points"):
            if key in entry:
                raise InputError(f"servo {servo!r}: give {key} inside the curve table", entry.path,
                                 entry.field(key))
        spec = entry.table("curve", _CURVE_KEYS)
        kind = spec.get("kind", str, "linear")
    else:
        spec, kind = entry, entry.get("curve", str, "linear")
    if kind not in CURVE_KINDS:
        raise InputError(f"servo {servo!r}: unknown curve {kind!r} ({', '.join(CURVE_KINDS)})", entry.path,
                         spec.field("kind") if spec is not entry else entry.field("curve"))
    for key, wanted in (("gamma", "gamma"), ("points", "piecewise")):
        if key in spec and kind != wanted:
            raise InputError(f"servo {servo!r}: {key} applies to a {wanted!r} curve, this one is {kind!r}",
                             entry.path, spec.field(key))
    gamma = spec.number("gamma", 1.0, 0.0, low_open=True)
    points = _points(spec.get("points", list, []), entry.path, spec.field("points"))
    try:
        return Curve(kind, gamma, points)
    except ValueError as error:
        raise InputError(f"servo {servo!r}: {error}", entry.path, entry.field("curve")) from None


def _points(value: list, path: str, field: str) -> tuple[tuple[float, float], ...]:
    points = []
    for k, point in enumerate(value):
        if not isinstance(point, list) or len(point) != 2:
            raise InputError(f"point {k}: expected [u, y], got {_describe(point)}", path, field)
        points.append(tuple(_in_range(v, -math.inf, math.inf, False, path, f"{field}[{k}]") for v in point))
    return tuple(points)


def _filter(entry: _Table, servo: str) -> Filter:
    """``filter = "none"`` or ``filter = { kind = ..., <that kind's parameters> }``."""
    if not isinstance(entry.data.get("filter"), dict):
        kind = entry.get("filter", str, "none")
        params = {}
    else:
        kind = entry.get("filter", dict).get("kind", "none")
        if not isinstance(kind, str) or kind not in _FILTER_KEYS:
            raise InputError(f"servo {servo!r}: unknown filter {kind!r} ({', '.join(_FILTER_KEYS)})", entry.path,
                             entry.field("filter.kind"))
        spec = entry.table("filter", _FILTER_KEYS[kind])
        params = {key: spec.number(key, None, 0.0) for key in _FILTER_KEYS[kind][1:] if key in spec}
    try:
        return Filter(kind, **params)
    except ValueError as error:
        raise InputError(f"servo {servo!r}: {error}", entry.path, entry.field("filter")) from None


def backup_path(path: str | Path) -> Path:
    """Where :func:`set_servo_limits` keeps the previous version of a rig file (``NAME.bak`` beside it)."""
    path = Path(path)
    return path.with_name(path.name + ".bak")


def set_servo_limits(path: str | Path, servo: str, minimum=None, neutral=None, maximum=None) -> Rig:
    """Record limits of one servo into the rig file; returns the new rig.

    The file is edited in place with its comments and layout kept (tomlkit), validated as it will be
    written, and replaced atomically; the previous file is kept at :func:`backup_path`.
    """
    path = Path(path)
    original = _read_bytes(path)
    try:
        document = tomlkit.parse(_decode(original, path))
    except tomlkit.exceptions.ParseError as error:
        raise InputError(f"not valid TOML ({error})", path) from None
    servos = document.get("servos")
    entry = servos.get(servo) if isinstance(servos, dict) else None
    if not isinstance(entry, dict):
        raise InputError(f"no servo {servo!r} in the rig", path, f"servos.{servo}")
    for key, value in (("min", minimum), ("neutral", neutral), ("max", maximum)):
        if value is not None:
            entry[key] = _toml_number(value, path, f"servos.{servo}.{key}")
    text = tomlkit.dumps(document)
    rig = rig_from_dict(tomllib.loads(text), path)  # exactly what will be on disk
    try:
        write_bytes_atomically(backup_path(path), original, "backup of the rig file", like=path)
        write_bytes_atomically(path, text.encode("utf-8"), "rig file", like=path)
    except OSError as error:
        raise InputError(f"cannot write the rig file ({error.strerror or error})", path) from None
    return rig


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputError("file not found", path) from None
    except IsADirectoryError:
        raise InputError("is a directory, not a rig file", path) from None
    except PermissionError:
        raise InputError("permission denied", path) from None


def _decode(data: bytes, path: str | Path) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise InputError(f"not UTF-8 text ({error.reason} at byte {error.start})", path) from None


def _toml_number(value: float, path: Path, field: str) -> int | float:
    """A raw limit as it reads best in the file: whole numbers without ``.0``."""
    value = _in_range(value, -math.inf, math.inf, False, str(path), field)
    return int(value) if value.is_integer() else value


def demo_rig(url: str = "simdynamixel://?ids=1-16&model=XL330-M288", muscle_names=None) -> Rig:
    """One servo per muscle on one bus (by default Dynamixel ids 1..16): a ready rig for demos and benchmarks.

    Each servo swings its driver's typical span around the centre, from the family's first address on.
    """
    names = tuple(muscle_names) if muscle_names is not None else default_muscle_names()
    facts = bus_facts(url)
    neutral, span = facts.centre, facts.typical_span
    servos = []
    for i, muscle in enumerate(names):
        inverted = i % 2 == 1  # mirrored mounting on the right side
        servos.append(ServoSpec(muscle, "head", facts.first_address + i, ((muscle, 1.0),), neutral,
                                neutral - (0.5 * span if not inverted else -0.5 * span),
                                neutral + (span if not inverted else -span), slew=span * 4,
                                filter=Filter("exponential", tau=0.02)))
    return Rig({"head": BusSpec("head", url, facts)}, tuple(servos))

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

Unknown muscle names, two servos on one bus address, limits outside the
device's range and a neutral outside [min, max] raise :class:`InputError`
naming the file and the servo.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from livebridge.devices.registry import bus_facts
from livebridge.errors import InputError
from livebridge.servo.bus import BusFacts
from livebridge.servo.mapping import Curve, Mapping
from livebridge.servo.safety import Filter, SafetyMapper
from livebridge.tomlio import load_toml, require, save_toml


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
    return rig_from_dict(load_toml(path), path, muscle_names)


def _number(table, key, path, prefix, default=None, positive=False) -> float:
    if key not in table and default is not None:
        return float(default)
    value = float(require(table, key, (int, float), path, prefix))
    if not math.isfinite(value) or (positive and value <= 0):
        raise InputError(f"must be a finite {'positive ' if positive else ''}number, got {value}", path,
                         f"{prefix}.{key}")
    return value


def rig_from_dict(data: dict[str, Any], path: str | Path | None = None, muscle_names=None) -> Rig:
    """Validate a parsed rig file; ``muscle_names`` defaults to the Choe-Ko 16."""
    path = str(path) if path is not None else "<rig>"
    known = tuple(muscle_names) if muscle_names is not None else default_muscle_names()
    frame_rate = _number(data, "frame_rate", path, "", 50.0, positive=True)
    safety = data.get("safety", {})
    if not isinstance(safety, dict):
        raise InputError("expected a table", path, "safety")
    estop = safety.get("estop", "stop")
    if estop not in ("stop", "home"):
        raise InputError(f"estop must be 'stop' or 'home', got {estop!r}", path, "safety.estop")
    buses_table = require(data, "buses", dict, path)
    buses = {}
    for name, entry in buses_table.items():
        if not isinstance(entry, dict):
            raise InputError("expected a table with url", path, f"buses.{name}")
        url = require(entry, "url", str, path, f"buses.{name}")
        try:
            facts = bus_facts(url)
        except InputError as error:
            raise InputError(error.message, path, f"buses.{name}.url") from None
        buses[name] = BusSpec(name, url, facts)
    servos_table = require(data, "servos", dict, path)
    servos = []
    used: dict[tuple[str, int], str] = {}
    for name, entry in servos_table.items():
        prefix = f"servos.{name}"
        if not isinstance(entry, dict):
            raise InputError("expected a table", path, prefix)
        bus = require(entry, "bus", str, path, prefix)
        if bus not in buses:
            raise InputError(f"servo {name!r}: unknown bus {bus!r} (known: {', '.join(buses)})", path,
                             f"{prefix}.bus")
        facts = buses[bus].facts
        key = "id" if "id" in entry else "channel"
        address = require(entry, key, int, path, prefix)
        lo, hi = facts.address_range
        if not lo <= address <= hi:
            raise InputError(f"servo {name!r}: {key} {address} outside {lo}..{hi} for a {facts.kind} bus", path,
                             f"{prefix}.{key}")
        if (bus, address) in used:
            raise InputError(f"servo {name!r} and servo {used[bus, address]!r} both use {key} {address} on bus "
                             f"{bus!r}", path, f"{prefix}.{key}")
        used[bus, address] = name
        muscles_table = require(entry, "muscles", dict, path, prefix)
        if not muscles_table:
            raise InputError(f"servo {name!r}: no muscles drive it", path, f"{prefix}.muscles")
        muscles = []
        for muscle in muscles_table:
            if muscle not in known:
                raise InputError(f"servo {name!r}: unknown muscle {muscle!r} (known: {', '.join(known)})", path,
                                 f"{prefix}.muscles.{muscle}")
            w = _number(muscles_table, muscle, path, f"{prefix}.muscles")
            muscles.append((muscle, w))
        neutral = _number(entry, "neutral", path, prefix)
        minimum = _number(entry, "min", path, prefix)
        maximum = _number(entry, "max", path, prefix)
        low, high = min(minimum, maximum), max(minimum, maximum)
        dev_lo, dev_hi = facts.raw_range
        if low < dev_lo or high > dev_hi:
            raise InputError(f"servo {name!r}: limits {minimum:g}..{maximum:g} outside the {facts.kind} range "
                             f"{dev_lo:g}..{dev_hi:g}", path, prefix)
        if low == high:
            raise InputError(f"servo {name!r}: min and max are equal", path, prefix)
        if not low <= neutral <= high:
            raise InputError(f"servo {name!r}: neutral {neutral:g} outside {low:g}..{high:g}", path,
                             f"{prefix}.neutral")
        slew = _number(entry, "slew", path, prefix, default=(high - low) * 2.0, positive=True)
        try:
            curve = _curve(entry)
        except (ValueError, TypeError) as error:
            raise InputError(f"servo {name!r}: {error}", path, f"{prefix}.curve") from None
        try:
            filt = _filter(entry.get("filter", "none"))
        except (ValueError, TypeError) as error:
            raise InputError(f"servo {name!r}: {error}", path, f"{prefix}.filter") from None
        model = entry.get("model")
        if model is not None and not isinstance(model, str):
            raise InputError(f"servo {name!r}: model must be a string", path, f"{prefix}.model")
        servos.append(ServoSpec(name, bus, address, tuple(muscles), neutral, minimum, maximum, slew, curve, filt,
                                model))
    return Rig(buses, tuple(servos), frame_rate, _number(safety, "watchdog_s", path, "safety", 0.5, True),
               _number(safety, "soft_start_s", path, "safety", 1.5), _number(safety, "ease_s", path, "safety", 2.0,
                                                                              True), estop, path)


def _curve(entry: dict) -> Curve:
    spec = entry.get("curve", "linear")
    if isinstance(spec, str):
        spec = {"kind": spec, "gamma": entry.get("gamma", 1.0), "points": entry.get("points", ())}
    if not isinstance(spec, dict):
        raise TypeError("curve must be a name or a table")
    points = tuple(tuple(float(v) for v in p) for p in spec.get("points", ()))
    return Curve(str(spec.get("kind", "linear")), float(spec.get("gamma", 1.0)), points)


def _filter(spec) -> Filter:
    if isinstance(spec, str):
        return Filter(spec)
    if not isinstance(spec, dict):
        raise TypeError("filter must be a name or a table")
    spec = dict(spec)
    unknown = set(spec) - {"kind", "tau", "min_cutoff", "beta", "d_cutoff"}
    if unknown:
        raise ValueError(f"unknown filter keys {sorted(unknown)}")
    return Filter(**{k: (float(v) if k != "kind" else str(v)) for k, v in spec.items()})


def set_servo_limits(path: str | Path, servo: str, minimum=None, neutral=None, maximum=None) -> Rig:
    """Record limits of one servo into the rig file (validated before writing); returns the new rig."""
    data = load_toml(path)
    entry = data.get("servos", {}).get(servo)
    if entry is None:
        raise InputError(f"no servo {servo!r} in the rig", path, f"servos.{servo}")
    for key, value in (("min", minimum), ("neutral", neutral), ("max", maximum)):
        if value is not None:
            entry[key] = float(value)
    rig = rig_from_dict(data, path)
    save_toml(path, data)
    return rig


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

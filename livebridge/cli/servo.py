"""``livebridge servo``: set up a real head: find servos, move one gently, record its limits.

Every numeric option is checked (finite, inside the bus's or the servo's range, speed > 0, a jog that
ends within :data:`JOG_MAX_S`) before a bus is opened, so a refused command sends nothing.
"""

from __future__ import annotations

import math
import time

import click

from livebridge.cli._options import InputPath, inside, parse_addresses, positive

JOG_PERIOD_S = 0.02
"""One target every this many seconds while jogging."""
JOG_SETTLE_S = 0.2
"""Wait after the last target before reading where the servo ended."""
JOG_MAX_S = 60.0
"""The longest move ``jog`` makes; a --speed that could take longer is refused."""


def _facts(url: str):
    from livebridge.devices.registry import bus_facts
    from livebridge.errors import InputError

    try:
        return bus_facts(url)
    except InputError as error:
        raise click.BadParameter(str(error), param_hint="URL") from None


def _open(url: str):
    from livebridge.devices.registry import open_bus

    return open_bus(url, log=lambda m: click.echo(m, err=True))


@click.group()
def servo() -> None:
    """Servo setup: scan a bus, jog one servo, record limits into a rig file."""


@servo.command()
@click.argument("url")
@click.option("--ids", default=None, help="Only these IDs/channels (e.g. 1-20); default: broadcast ping / all.")
def scan(url: str, ids: str | None) -> None:
    """List the servos that answer on bus URL (e.g. dynamixel:///dev/ttyUSB0?baud=1000000)."""
    facts = _facts(url)
    addresses = None if ids is None else parse_addresses(ids, *facts.address_range, "--ids")
    bus = _open(url)
    try:
        found = bus.scan(addresses)
        for info in found:
            extra = f" firmware {info.firmware}" if info.firmware is not None else ""
            number = f" (model number {info.model_number})" if info.model_number is not None else ""
            click.echo(f"{info.address:3d}  {info.model or 'unknown'}{number}{extra}")
        click.echo(f"{len(found)} found", err=True)
    finally:
        bus.close()


@servo.command()
@click.argument("url")
@click.option("--id", "address", type=int, required=True, help="Servo ID (Dynamixel) or channel.")
@click.option("--to", "goal", type=float, default=None, help="Raw target to move to (inside --low..--high).")
@click.option("--by", "delta", type=float, default=None,
              help="Raw amount to move by from the present position (stops at --low/--high).")
@click.option("--speed", type=float, default=200.0, show_default=True,
              help=f"Raw units per second (> 0; a move takes at most {JOG_MAX_S:g} s).")
@click.option("--low", type=float, default=None, help="Never go below (default: device range).")
@click.option("--high", type=float, default=None, help="Never go above (default: device range).")
@click.option("--hold", is_flag=True, help="Keep torque on at the end (default: torque off).")
def jog(url: str, address: int, goal: float | None, delta: float | None, speed: float, low, high, hold) -> None:
    """Move one servo gently to --to or --by, ramping at --speed, and print where it ended."""
    from livebridge.servo.bus import ServoSetup

    if (goal is None) == (delta is None):
        raise click.UsageError("give exactly one of --to and --by")
    facts = _facts(url)
    first, last = facts.address_range
    inside(address, first, last, "--id", f"the {facts.kind} addresses")
    low, high = _jog_limits(facts, low, high)
    if goal is not None:
        inside(goal, low, high, "--to", "--low..--high")
        distance = max(goal - low, high - goal)  # the present position may be anywhere in low..high
    else:
        inside(delta, -(high - low), high - low, "--by", "± the span of --low..--high")
        distance = abs(delta)
    _jog_speed(speed, distance)
    centre = min(high, max(low, facts.centre))  # where a servo that reports no position is assumed to be
    bus = _open(url)
    try:
        bus.configure([ServoSetup(address, low, high, centre, name=f"{address}")], JOG_PERIOD_S)
        present = bus.activate().get(address, math.nan)
        start = min(high, max(low, present)) if math.isfinite(present) else centre
        target = goal if goal is not None else min(high, max(low, start + delta))
        _ramp(bus, address, start, target, speed)
        time.sleep(JOG_SETTLE_S)
        status = bus.poll().get(address)
        stopped = " (stopped at the limit)" if goal is None and target != start + delta else ""
        click.echo(f"id {address}: from {start:g} to {target:g}{stopped}; now at "
                   f"{status.position if status and status.position is not None else 'unknown'}")
    finally:
        try:
            if not hold:
                bus.deactivate()
        finally:
            bus.close()


def _jog_limits(facts, low: float | None, high: float | None) -> tuple[float, float]:
    """--low and --high checked against the device's raw range (default: that range)."""
    lo_dev, hi_dev = facts.raw_range
    what = f"the {facts.kind} range"
    low = lo_dev if low is None else inside(low, lo_dev, hi_dev, "--low", what)
    high = hi_dev if high is None else inside(high, lo_dev, hi_dev, "--high", what)
    if not low < high:
        raise click.BadParameter(f"--low {low:g} must be below --high {high:g}", param_hint="--low/--high")
    return low, high


def _jog_speed(speed: float, distance: float) -> None:
    """Refuse a --speed that is not > 0 or would make a move of up to ``distance`` outlast :data:`JOG_MAX_S`."""
    positive(speed, "--speed", "raw units per second")
    if distance / speed > JOG_MAX_S:
        raise click.BadParameter(f"{speed:g} raw units/s could take {distance / speed:.0f} s for this move; a jog "
                                 f"takes at most {JOG_MAX_S:g} s (raise --speed or jog in shorter moves)",
                                 param_hint="--speed")


def _ramp(bus, address: int, start: float, target: float, speed: float) -> None:
    """Write targets from ``start`` to ``target`` at ``speed`` raw units/s, one every :data:`JOG_PERIOD_S`.

    Paced by the clock, not by counting writes, so a slow bus cannot stretch the move past its duration.
    """
    duration = abs(target - start) / speed
    t0 = time.monotonic()
    while True:
        s = 1.0 if duration <= 0 else min(1.0, (time.monotonic() - t0) / duration)
        bus.write({address: start + (target - start) * s})
        if s >= 1.0:
            return
        time.sleep(JOG_PERIOD_S)


@servo.command()
@click.argument("rig_file", type=InputPath())
@click.argument("servo_name")
@click.option("--min", "minimum", type=float, default=None, help="Raw limit reached at drive -1.")
@click.option("--neutral", type=float, default=None, help="Raw target at rest.")
@click.option("--max", "maximum", type=float, default=None, help="Raw limit reached at drive +1.")
@click.option("--from-present", type=click.Choice(["min", "neutral", "max"]), default=None,
              help="Read the servo's present position (torque off: move it by hand) and record it as this limit.")
def limits(rig_file: str, servo_name: str, minimum, neutral, maximum, from_present) -> None:
    """Record min / neutral / max of SERVO_NAME into RIG_FILE (validated before writing).

    The file keeps its comments and layout; the previous version is kept as RIG_FILE.bak.
    """
    from livebridge.servo.rig import backup_path, load_rig, set_servo_limits

    rig = load_rig(rig_file)
    try:
        spec = rig.servo(servo_name)
    except KeyError:
        raise click.BadParameter(f"{rig_file} has no servo {servo_name!r}", param_hint="SERVO_NAME") from None
    values = {"min": minimum, "neutral": neutral, "max": maximum}
    facts = rig.buses[spec.bus].facts
    for key, value in values.items():
        inside(value, *facts.raw_range, f"--{key}", f"the {facts.kind} range for servo {servo_name!r}")
    if from_present:
        if values[from_present] is not None:
            raise click.UsageError(f"give --{from_present} or --from-present {from_present}, not both")
        values[from_present] = _present_position(rig, spec)
    if all(v is None for v in values.values()):
        raise click.UsageError("nothing to record: give --min/--neutral/--max or --from-present")
    rig = set_servo_limits(rig_file, servo_name, values["min"], values["neutral"], values["max"])
    s = rig.servo(servo_name)
    click.echo(f"{servo_name}: min {s.minimum:g}  neutral {s.neutral:g}  max {s.maximum:g} "
               f"(previous file kept as {backup_path(rig_file)})")


def _present_position(rig, spec) -> float:
    """The raw position of one servo of the rig, read with torque off (to be moved by hand)."""
    from livebridge.servo.bus import ServoSetup

    bus_spec = rig.buses[spec.bus]
    lo, hi = bus_spec.facts.raw_range
    bus = _open(bus_spec.url)
    try:
        bus.configure([ServoSetup(spec.address, lo, hi, spec.neutral, spec.model, spec.name)], JOG_PERIOD_S)
        bus.deactivate()
        status = bus.poll().get(spec.address)
    finally:
        bus.close()
    if status is None or status.position is None or not math.isfinite(status.position):
        raise click.ClickException(f"{spec.name}: this bus reports no position")
    return status.position

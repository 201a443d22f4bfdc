"""``livebridge servo``: set up a real head: find servos, move one gently, record its limits."""

from __future__ import annotations

import time

import click


def _parse_ids(text: str | None):
    if text is None:
        return None
    from livebridge.simulators.dynamixel_bus import parse_ids

    try:
        return parse_ids(text)
    except ValueError as error:
        raise click.BadParameter(str(error), param_hint="--ids") from None


@click.group()
def servo() -> None:
    """Servo setup: scan a bus, jog one servo, record limits into a rig file."""


@servo.command()
@click.argument("url")
@click.option("--ids", default=None, help="Only these IDs/channels (e.g. 1-20); default: broadcast ping / all.")
def scan(url: str, ids: str | None) -> None:
    """List the servos that answer on bus URL (e.g. dynamixel:///dev/ttyUSB0?baud=1000000)."""
    from livebridge.devices.registry import open_bus
    from livebridge.errors import InputError

    try:
        bus = open_bus(url, log=lambda m: click.echo(m, err=True))
    except InputError as error:
        raise click.ClickException(str(error)) from None
    try:
        found = bus.scan(_parse_ids(ids))
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
@click.option("--to", "goal", type=float, default=None, help="Raw target to move to.")
@click.option("--by", "delta", type=float, default=None, help="Raw amount to move by from the present position.")
@click.option("--speed", type=float, default=200.0, show_default=True, help="Raw units per second.")
@click.option("--low", type=float, default=None, help="Never go below (default: device range).")
@click.option("--high", type=float, default=None, help="Never go above (default: device range).")
@click.option("--hold", is_flag=True, help="Keep torque on at the end (default: torque off).")
def jog(url: str, address: int, goal: float | None, delta: float | None, speed: float, low, high, hold) -> None:
    """Move one servo gently to --to or --by, ramping at --speed, and print where it ended."""
    import math

    from livebridge.devices.registry import bus_facts, open_bus
    from livebridge.errors import InputError
    from livebridge.servo.bus import ServoSetup

    if (goal is None) == (delta is None):
        raise click.UsageError("give exactly one of --to and --by")
    try:
        lo_dev, hi_dev = bus_facts(url).raw_range
        low = lo_dev if low is None else max(lo_dev, low)
        high = hi_dev if high is None else min(hi_dev, high)
        bus = open_bus(url, log=lambda m: click.echo(m, err=True))
        bus.configure([ServoSetup(address, low, high, (low + high) / 2, name=f"{address}")], 0.02)
        present = bus.activate().get(address, math.nan)
    except InputError as error:
        raise click.ClickException(str(error)) from None
    try:
        start = present if math.isfinite(present) else (low + high) / 2
        target = goal if goal is not None else start + delta
        target = min(high, max(low, target))
        steps = max(1, int(abs(target - start) / max(speed, 1e-6) / 0.02))
        for k in range(1, steps + 1):
            bus.write({address: start + (target - start) * k / steps})
            time.sleep(0.02)
        time.sleep(0.2)
        status = bus.poll().get(address)
        click.echo(f"id {address}: from {start:g} to {target:g}; now at "
                   f"{status.position if status and status.position is not None else 'unknown'}")
    finally:
        if not hold:
            bus.deactivate()
        bus.close()


@servo.command()
@click.argument("rig_file", type=click.Path(exists=True, dir_okay=False))
@click.argument("servo_name")
@click.option("--min", "minimum", type=float, default=None)
@click.option("--neutral", type=float, default=None)
@click.option("--max", "maximum", type=float, default=None)
@click.option("--from-present", type=click.Choice(["min", "neutral", "max"]), default=None,
              help="Read the servo's present position (torque off: move it by hand) and record it as this limit.")
def limits(rig_file: str, servo_name: str, minimum, neutral, maximum, from_present) -> None:
    """Record min / neutral / max of SERVO_NAME into RIG_FILE (validated before writing)."""
    import math

    from livebridge.devices.registry import open_bus
    from livebridge.errors import InputError
    from livebridge.servo.bus import ServoSetup
    from livebridge.servo.rig import load_rig, set_servo_limits

    try:
        rig = load_rig(rig_file)
        spec = rig.servo(servo_name)
    except KeyError:
        raise click.ClickException(f"{rig_file}: no servo {servo_name!r}") from None
    except InputError as error:
        raise click.ClickException(str(error)) from None
    values = {"min": minimum, "neutral": neutral, "max": maximum}
    if from_present:
        bus_spec = rig.buses[spec.bus]
        lo, hi = bus_spec.facts.raw_range
        bus = open_bus(bus_spec.url, log=lambda m: click.echo(m, err=True))
        try:
            bus.configure([ServoSetup(spec.address, lo, hi, spec.neutral, spec.model, spec.name)], 0.02)
            bus.deactivate()
            status = bus.poll().get(spec.address)
            if status is None or status.position is None or not math.isfinite(status.position):
                raise click.ClickException(f"{servo_name}: this bus reports no position")
            values[from_present] = status.position
        finally:
            bus.close()
    if all(v is None for v in values.values()):
        raise click.UsageError("nothing to record: give --min/--neutral/--max or --from-present")
    try:
        rig = set_servo_limits(rig_file, servo_name, values["min"], values["neutral"], values["max"])
    except InputError as error:
        raise click.ClickException(str(error)) from None
    s = rig.servo(servo_name)
    click.echo(f"{servo_name}: min {s.minimum:g}  neutral {s.neutral:g}  max {s.maximum:g}")

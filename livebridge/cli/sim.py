"""``livebridge sim``: serve simulated servo buses on pseudo-terminals.

Each command prints the pseudo-terminal path as its first line, then serves
until stopped (Ctrl-C / SIGTERM). Point any client at that path: our
drivers, the vendor SDK, a terminal program.
"""

from __future__ import annotations

import signal
import sys
import threading

import click

from livebridge.cli._options import PROBABILITY, SEED, parse_addresses


def _serve(sim, describe: str) -> None:
    path = sim.start()
    click.echo(path)
    sys.stdout.flush()
    click.echo(describe, err=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        while not stop.wait(0.5):
            if sim.pty is not None and sim.pty.error is not None:
                break
    finally:
        sim.close()


@click.group()
def sim() -> None:
    """Simulated servo buses that speak the real wire protocols on a pseudo-terminal."""


@sim.command()
@click.option("--ids", default="1", show_default=True, help="Servo IDs, e.g. 1-16 or 1,3,5.")
@click.option("--model", default="XL330-M288", show_default=True, help="XL330-M288, XL330-M077, XM430-W350, ...")
@click.option("--baud", default=1_000_000, show_default=True, help="Baud rate the servos are set to.")
@click.option("--corrupt", type=PROBABILITY, default=0.0, show_default=True,
              help="Probability a reply gets a flipped byte.")
@click.option("--drop", type=PROBABILITY, default=0.0, show_default=True, help="Probability a reply is not sent.")
@click.option("--seed", type=SEED, default=0, show_default=True)
@click.option("--delay", type=click.IntRange(0, 254), default=None,
              help="Return delay time of every servo (2 µs units).")
def dynamixel(ids: str, model: str, baud: int, corrupt: float, drop: float, seed: int, delay: int | None) -> None:
    """A DYNAMIXEL Protocol 2.0 bus of X-series servos."""
    from livebridge.drivers.dynamixel_protocol import BAUD_CODES, MAX_ID, MODELS
    from livebridge.simulators.dynamixel_bus import DynamixelSim

    if model not in MODELS:
        raise click.BadParameter(f"unknown model {model!r}; known: {', '.join(MODELS)}", param_hint="--model")
    id_list = parse_addresses(ids, 0, MAX_ID, "--ids")
    if baud not in BAUD_CODES.values():
        raise click.BadParameter(f"{baud} is not a DYNAMIXEL baud rate ({', '.join(map(str, BAUD_CODES.values()))})",
                                 param_hint="--baud")
    bus = DynamixelSim(ids=id_list, model=model, baud=baud, corrupt_rate=corrupt, drop_rate=drop, seed=seed,
                       return_delay_time=delay)
    _serve(bus, f"simulated DYNAMIXEL bus: {len(id_list)} x {model} at {baud} baud (ids {ids}); Ctrl-C stops")


@sim.command()
@click.option("--channels", type=click.IntRange(1, 24), default=24, show_default=True,  # the largest Maestro
              help="Number of channels (6, 12, 18 or 24 on real Maestros).")
@click.option("--device", type=click.IntRange(0, 127), default=12, show_default=True,
              help="Pololu-protocol device number.")
@click.option("--corrupt", type=PROBABILITY, default=0.0, show_default=True)
@click.option("--drop", type=PROBABILITY, default=0.0, show_default=True)
@click.option("--seed", type=SEED, default=0, show_default=True)
def maestro(channels: int, device: int, corrupt: float, drop: float, seed: int) -> None:
    """A Pololu Maestro (compact and Pololu protocols)."""
    from livebridge.simulators.maestro_bus import MaestroSim

    bus = MaestroSim(channels=channels, device=device, corrupt_rate=corrupt, drop_rate=drop, seed=seed)
    _serve(bus, f"simulated Maestro: {channels} channels, device {device}; Ctrl-C stops")


@sim.command()
@click.option("--corrupt", type=PROBABILITY, default=0.0, show_default=True)
@click.option("--drop", type=PROBABILITY, default=0.0, show_default=True)
@click.option("--seed", type=SEED, default=0, show_default=True)
def ssc32(corrupt: float, drop: float, seed: int) -> None:
    """A Lynxmotion SSC-32U (ASCII protocol)."""
    from livebridge.simulators.ssc32_bus import SSC32Sim

    _serve(SSC32Sim(corrupt_rate=corrupt, drop_rate=drop, seed=seed), "simulated SSC-32U; Ctrl-C stops")

"""``livebridge play``: drive the head (and the render client) from a contraction file.

Capture once, clean the contractions, then perform them on the head: through the same safety stage as
the live path (limits, slew, soft start, watchdog), paced by the file's time column. See
:mod:`livebridge.servo.playback` for what is done with gaps, holes and stray values in a file.
"""

from __future__ import annotations

import click

from livebridge.cli._options import FiniteFloat, InputPath, Port

MAX_SPEED = 100.0
"""The fastest --speed accepted (file seconds per second)."""


@click.command()
@click.argument("contractions", type=InputPath())
@click.option("--rig", "rig_file", type=InputPath(), required=True, help="Servo rig file (rig.toml).")
@click.option("--basis", "basis_spec", type=InputPath(builtins=("builtin",)), default="builtin", show_default=True,
              help="Basis (.npz or 'builtin'): its muscles are the file's columns; the render client shows it.")
@click.option("--speed", type=FiniteFloat(0.0, MAX_SPEED, low_open=True), default=1.0, show_default=True,
              help="File seconds per second (0.5: half speed).")
@click.option("--loop", is_flag=True, help="Start again at the end, until Ctrl-C.")
@click.option("--ignore-extra", is_flag=True, help="Leave out columns that are no muscle of the basis.")
@click.option("--render/--no-render", default=False, show_default=True, help="Also serve the render client.")
@click.option("--port", type=Port(any_free=True), default=8765, show_default=True,
              help="Render client port (0: any free port).")
def play(contractions, rig_file, basis_spec, speed: float, loop: bool, ignore_extra: bool, render: bool,
         port: int) -> None:
    """Play CONTRACTIONS (CSV: a time column t/time in seconds + one column per muscle) on the servos of --rig.

    Ctrl-C eases every servo to neutral and turns torque off.
    """
    from livebridge.cli.markers import load_basis
    from livebridge.servo import playback
    from livebridge.servo.output import ServoOutput
    from livebridge.servo.rig import load_rig

    basis = load_basis(basis_spec)
    track = playback.read_contractions(contractions, basis.names, ignore_extra)
    rig = load_rig(rig_file, basis.names)
    for note in track.notes:
        click.echo(f"{contractions}: {note}", err=True)
    output = ServoOutput(rig, basis.names, clock=playback.CLOCK, log=lambda m: click.echo(m, err=True),
                         poll_every=max(1, round(rig.frame_rate / 4)))
    server = None
    try:
        output.configure()
        publish = None
        if render:
            server, publish = _render(basis, output, port)
            click.echo(f"render client: {server.url}", err=True)
        click.echo(f"playing {contractions}: {len(track.t)} rows, {track.duration:.2f} s at speed {speed:g}"
                   f"{', looping (Ctrl-C to stop)' if loop else ''}", err=True)
        report = playback.play(track, output, speed, loop, publish, log=lambda m: click.echo(m, err=True))
        click.echo(f"played {report.frames} frames; servos eased to neutral, torque off", err=True)
    finally:
        output.close(ease=False)
        if server is not None:
            server.stop()


def _render(basis, output, port: int):
    """A started render server and the per-frame callback that publishes to it."""
    import numpy as np

    from livebridge.output.render_server import RenderFrame, RenderServer

    server = RenderServer(basis, None, "127.0.0.1", port, servo_names=output.servo_names).start()
    low, span = output.mapper.low, output.mapper.span

    def publish(seq, t, contractions, raw):
        targets = (np.asarray(raw, dtype=np.float64) - low) / span
        server.publish(RenderFrame(seq, t, np.asarray(contractions, dtype=np.float64), servo_targets=targets))

    return server, publish

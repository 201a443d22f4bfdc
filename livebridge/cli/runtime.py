"""``livebridge run SESSION`` and ``livebridge demo``: the live pipeline from the command line."""

from __future__ import annotations

import sys

import click

from livebridge.cli._options import (
    FRAMES,
    SEED,
    BindHost,
    Destination,
    FiniteFloat,
    InputPath,
    NewFolder,
    Port,
    Size,
    allow_remote_option,
    bind_host_problem,
    render_bind_problem,
)

# The demo's camera options, as the simulated rig bounds them (simulators.rig: _CONFIG_RANGES["fps"], SIZE_RANGE).
DEMO_FPS = (1.0, 1000.0)
DEMO_SIZE = (16, 4096)


def _log(message: str) -> None:
    click.echo(message, err=True)


def _announce_outputs(pipeline) -> None:
    """The start-up banner's output lines: where the frames go (each says so when they leave this machine)."""
    for output in pipeline.outputs:
        click.echo(output.describe())


def _print_summary(summary, score=None, pipeline=None) -> None:
    """The end-of-run summary; ``score`` (a simulator's ground-truth score) describes its own line."""
    from livebridge.runtime.pipeline import milliseconds

    if pipeline is not None and pipeline.front.kind == "livelink":
        _print_livelink_summary(summary, score, pipeline)
        return
    click.echo(f"frame sets solved: {summary.solved} ({summary.framesets} reconstructed), "
               f"{summary.fps:.1f} per second, {summary.drops} dropped")
    click.echo(f"latency (frame set complete -> servo bytes written): p50 {milliseconds(summary.latency_p50_ms)}, "
               f"p99 {milliseconds(summary.latency_p99_ms)}; render message sent: p50 "
               f"{milliseconds(summary.render_latency_p50_ms)}, p99 {milliseconds(summary.render_latency_p99_ms)}")
    if summary.labelled_fraction == summary.labelled_fraction:  # a marker front (NaN elsewhere)
        click.echo(f"labelled markers {100 * summary.labelled_fraction:.2f}%, marker error upper "
                   f"{summary.error_upper_mm:.3f} mm, lower {summary.error_lower_mm:.3f} mm; "
                   f"cameras alive {summary.cameras_alive}/{summary.cameras}")
    elif summary.quality:
        figures = ", ".join(f"{name} {value:.3f}" for name, value in summary.quality)
        click.echo(f"quality (mean of the last frames): {figures}; cameras alive {summary.cameras_alive}/"
                   f"{summary.cameras}")
    if summary.frames_skipped:
        per_camera = ", ".join(f"{name} {count}" for name, count in summary.frames_skipped)
        click.echo(f"frames skipped (damaged or missing images): {summary.frames_skipped_total} ({per_camera})")
    if score is not None:
        click.echo(score.describe())


def _print_livelink_summary(summary, score, pipeline) -> None:
    """The summary of a Live Link Face run: packets instead of frame sets and markers."""
    from livebridge.runtime.pipeline import milliseconds

    front = pipeline.front
    receiver = front.receiver
    click.echo(f"packets solved: {summary.solved}, {summary.fps:.1f} per second; superseded by a newer one "
               f"{receiver.superseded}")
    what = "servo bytes written" if pipeline.servo is not None else "solved"
    click.echo(f"latency (packet arrival -> {what}): p50 {milliseconds(summary.latency_p50_ms)}, p99 "
               f"{milliseconds(summary.latency_p99_ms)}; render message sent: p50 "
               f"{milliseconds(summary.render_latency_p50_ms)}, p99 {milliseconds(summary.render_latency_p99_ms)}")
    click.echo(f"phone: {receiver.received} datagrams, {receiver.lost} lost, refused {front.refused_text()}")
    if score is not None:
        click.echo(score.describe())


EXIT_CAMERA_FAILED = 1


def _exit_on_camera_errors(summary) -> None:
    """After the summary: one line per camera that failed during the run, and a non-zero exit code."""
    for name, error in summary.camera_errors:
        click.echo(f"Error: camera {name} failed during the run: {error}", err=True)
    if summary.camera_errors:
        raise click.exceptions.Exit(EXIT_CAMERA_FAILED)


def _check_render_address(session, allow_remote: bool) -> None:
    """Refuse, before the long set-up, a render host other machines reach (without --allow-remote) and a
    port another program holds (the server's own bind still reports one taken in between)."""
    from livebridge.errors import InputError

    render = session.render
    if not render.enabled:
        return
    problem = None if allow_remote else bind_host_problem(render.host)
    if problem is not None:
        raise InputError(problem, session.path, "outputs.render.host")
    clash = render_bind_problem(render.host, render.port)
    if clash is not None:
        raise InputError(clash[1], session.path, f"outputs.render.{clash[0]}")


@click.command()
@click.argument("session", type=InputPath())
@click.option("--frames", type=FRAMES, default=None,
              help="Stop after this many frame sets (default: the session's, or until Ctrl-C).")
@allow_remote_option
def run(session: str, frames: int | None, allow_remote: bool) -> None:
    """Run the live pipeline described by the session file SESSION (Ctrl-C stops it in order)."""
    from livebridge.runtime.build import build_pipeline
    from livebridge.runtime.pipeline import run_until_stopped
    from livebridge.runtime.session import load_session

    loaded = load_session(session)
    _check_render_address(loaded, allow_remote)
    pipeline = build_pipeline(loaded, log=_log)

    def started(p):
        if p.render is not None:
            click.echo(f"render client: {p.render.url}")
        _announce_outputs(p)
        sys.stdout.flush()

    summary = run_until_stopped(pipeline, frames if frames is not None else loaded.frames, log=_log,
                                on_start=started)
    _print_summary(summary, pipeline=pipeline)
    _exit_on_camera_errors(summary)


RIG_ONLY = ("cameras", "fps", "size", "unpaced", "record_frames")


@click.command()
@click.option("--source", type=click.Choice(["rig", "livelinkface"]), default="rig", show_default=True,
              help="rig: a simulated 4-camera rig filming a face with markers; livelinkface: a simulated iPhone "
                   "sending Live Link Face packets (60 Hz, loopback).")
@click.option("--frames", type=FRAMES, default=0, help="End after N frame sets (packets) and print a summary.")
@click.option("--cameras", type=click.IntRange(2, 8), default=4, show_default=True, help="Simulated cameras.")
@click.option("--seed", type=SEED, default=1, show_default=True)
@click.option("--fps", type=FiniteFloat(*DEMO_FPS), default=30.0, show_default=True,
              help="Camera frame rate (30 keeps up on a 2-core machine; real rigs run 30-120).")
@click.option("--size", type=Size(*DEMO_SIZE), default="1280x800", show_default=True,
              help="Simulated image size WxH.")
@click.option("--host", type=BindHost(), default="127.0.0.1", show_default=True,
              help="Render client interface (not loopback: needs --allow-remote).")
@allow_remote_option
@click.option("--port", type=Port(any_free=True), default=8765, show_default=True,
              help="Render client port (0: any free port).")
@click.option("--unpaced", is_flag=True, help="Run the cameras as fast as the CPU allows instead of at --fps.")
@click.option("--no-servo", is_flag=True, help="Leave out the simulated servo bus.")
@click.option("--no-render", is_flag=True, help="Leave out the render client.")
@click.option("--vmc", type=Destination(), default=None, help="Also send VMC/OSC blendshapes there.")
@click.option("--record", type=NewFolder(), default=None,
              help="Record the take to this new folder (a phone's: its packets too, replay://FOLDER solves it again).")
@click.option("--record-frames", is_flag=True,
              help="With --record: also record the raw camera frames (replay them with replay://FOLDER).")
@click.option("--markerless", is_flag=True,
              help="One camera films a bare face with the LED head rig (light drifting, head turning), analysed "
                   "by co-articulation regions instead of markers.")
@click.option("--markerless-model", type=InputPath(), default=None,
              help="With --markerless: the model (.npz) to use; default: train one on a simulated training take.")
@click.option("--character", "character_spec", type=InputPath(kind="folder", builtins=("builtin",)), default=None,
              help="Also drive a 2D character in the render page: a character folder or 'builtin'.")
@click.pass_context
def demo(ctx, source, frames, cameras, seed, fps, size, host, allow_remote, port, unpaced, no_servo, no_render, vmc,
         record, record_frames, markerless, markerless_model, character_spec) -> None:
    """The whole pipeline on simulators: performer, 4-camera rig (or one camera with --markerless, or an
    iPhone with --source livelinkface), servo bus, render client.

    Prints the URL of the render page; Ctrl-C (or --frames N) ends it with a summary.
    """
    from livebridge.runtime.demo import build_demo, build_livelink_demo
    from livebridge.runtime.pipeline import run_until_stopped

    if record_frames and not record:
        raise click.BadParameter("needs --record FOLDER", param_hint="--record-frames")
    if source == "livelinkface":
        given = [name for name in RIG_ONLY
                 if ctx.get_parameter_source(name) is not click.core.ParameterSource.DEFAULT]
        if given:
            raise click.BadParameter("an option of the simulated rig; the phone has no cameras",
                                     param_hint=f"--{given[0].replace('_', '-')}")
    clash = None if no_render else render_bind_problem(host, port)
    if clash is not None:  # before the long set-up; the server's own bind still reports a port taken meanwhile
        raise click.BadParameter(clash[1], param_hint=f"--{clash[0]}")
    if markerless_model is not None and not markerless:
        raise click.BadParameter("needs --markerless", param_hint="--markerless-model")
    outputs = []  # filled once the pipeline (and its render server) exists

    def to_outputs(frame):
        for output in outputs:
            output.send(frame)

    if markerless and source == "livelinkface":
        raise click.BadParameter("the phone sends ARKit weights, not images", param_hint="--markerless")
    if source == "livelinkface":
        parts = build_livelink_demo(seed=seed, servo=not no_servo, render=not no_render, host=host, port=port,
                                    vmc=vmc, record=record, log=_log, on_frame=to_outputs)
    elif markerless:
        from livebridge.runtime.demo import build_markerless_demo

        parts = build_markerless_demo(seed=seed, fps=fps, realtime=not unpaced, servo=not no_servo,
                                      render=not no_render, host=host, port=port, model=markerless_model, log=_log,
                                      on_frame=to_outputs)
    else:
        parts = build_demo(cameras=cameras, seed=seed, fps=fps, size=size, realtime=not unpaced,
                           servo=not no_servo, render=not no_render, host=host, port=port, vmc=vmc, record=record,
                           record_frames=record_frames, log=_log, on_frame=to_outputs)
    if character_spec is not None:
        outputs.append(_character_output(character_spec, parts))

    def started(p):
        if p.render is not None:
            click.echo(f"livebridge demo: open {p.render.url} in a browser (Ctrl-C to stop)")
        else:
            click.echo("livebridge demo running (Ctrl-C to stop)")
        _announce_outputs(p)
        if parts.phone is not None:
            click.echo(f"simulated iPhone: Live Link Face packets at {parts.phone.fps:g} Hz to "
                       f"{p.front.receiver.url}")
            parts.phone.start()
        sys.stdout.flush()

    try:
        summary = run_until_stopped(parts.pipeline, frames, log=_log, on_start=started)
    finally:
        if parts.phone is not None:
            parts.phone.stop()
    _print_summary(summary, parts.score, parts.pipeline)
    for output in outputs:
        click.echo(f"2D character {output.character.name!r}: {output.frames} frames of region states "
                   f"({'shown in the render page' if output.server is not None else 'no render page'})")
        output.close()
    _exit_on_camera_errors(summary)


def _character_output(spec, parts):
    """A :class:`~livebridge.character.live.CharacterOutput` for the demo's muscles, shown in its render page."""
    from livebridge.character.live import CharacterOutput
    from livebridge.cli.character import load_character_spec
    from livebridge.cli.markers import load_basis

    muscle_names = load_basis(parts.session.basis).names
    return CharacterOutput(load_character_spec(spec), muscle_names, parts.pipeline.render)

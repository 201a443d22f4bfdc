"""``livebridge character``: 2D characters driven by the face (flip-book compositing, video rewrite)."""

from __future__ import annotations

from pathlib import Path

import click

from livebridge.cli._options import FiniteFloat, InputPath, NewFolder, OutputFile, force_option

CHARACTER_TYPE = InputPath(kind="folder", builtins=("builtin",))
FEATHER = FiniteFloat(0.0, 100.0)
MAX_FPS = 1000.0


@click.group("character")
def character() -> None:
    """2D characters: a neutral face and one sample per region state, composited from the performer's face."""


def load_character_spec(spec) -> object:
    """The character named by a command-line value: a character folder or ``builtin``."""
    if spec == "builtin":
        from livebridge.character.builtin import builtin_character

        return builtin_character()
    from livebridge.character.definition import load_character

    return load_character(spec)


def _load_model(path: Path):
    from livebridge.markerless.model import MarkerlessModel

    return MarkerlessModel.load(path)


@character.command("from-training")
@click.argument("model", type=InputPath())
@click.option("--out", required=True, type=NewFolder(), help="Character folder to create.")
@click.option("--feather", type=FEATHER, default=10.0, show_default=True,
              help="Width of the samples' alpha ramp, pixels (the paper's 10).")
def from_training(model: Path, out: Path, feather: float) -> None:
    """Fill a character from the training frames of MODEL (a markerless model, .npz): video rewrite.

    Each region's sample for a state is the region's pixels in the canonical frame that defines the state,
    so a new performance is rebuilt from the performer's own appearance.
    """
    from livebridge.character.definition import save_character
    from livebridge.character.rewrite import character_from_model

    built = character_from_model(_load_model(model), feather)
    manifest = save_character(built, out)
    n = sum(len(s) for region in built.regions for s in region.samples)
    click.echo(f"wrote {manifest}: {len(built.regions)} regions, {n} samples, {built.size[0]}x{built.size[1]}")


@character.command("template")
@click.argument("model", type=InputPath())
@click.option("--out", required=True, type=NewFolder(), help="Folder of guide sheets to create.")
def template(model: Path, out: Path) -> None:
    """Write guide sheets for an artist: per region and state of MODEL, the training frame with the region's
    mask, and the list of samples to draw (samples.csv, and a character.toml naming them)."""
    from livebridge.character.template import write_template

    listing, n = write_template(_load_model(model), out)
    click.echo(f"wrote {out}: {n} samples to draw, listed in {listing}")


def read_contraction_take(path: Path, basis_spec) -> tuple[object, object, tuple[str, ...]]:
    """``(t (n,), contractions (n, n_muscles), muscle names)`` of a take directory or a contraction CSV."""
    from livebridge.take.directory import is_take_dir, load_take_dir

    if path.is_dir():
        if not is_take_dir(path):
            from livebridge.errors import InputError

            raise InputError("not a take directory (no take.toml) and not a contraction file", path)
        take = load_take_dir(path)
        return take.t, take.contractions, take.muscle_names
    from livebridge.cli.markers import load_basis
    from livebridge.servo.playback import read_contractions

    track = read_contractions(path, load_basis(basis_spec).names)
    return track.t, track.values, track.muscle_names


@character.command("render")
@click.argument("take", type=InputPath(kind="any"))
@click.option("--character", "character_spec", required=True, type=CHARACTER_TYPE,
              help="Character folder, or 'builtin' (the procedural cartoon).")
@click.option("--out", required=True, type=OutputFile(),
              help="Video to write (.mp4/.mkv/.mov/.avi, H.264 with the 'video' extra); otherwise, or without "
                   "an encoder, a folder of numbered PNG frames.")
@force_option
@click.option("--basis", "basis_spec", type=InputPath(builtins=("builtin",)), default="builtin",
              show_default=True, help="Basis whose muscles a contraction CSV's columns are.")
@click.option("--fps", type=FiniteFloat(0.0, MAX_FPS, low_open=True), default=None,
              help="Frame rate of the video (default: the take's).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
def render(take: Path, character_spec, out: Path, force: bool, basis_spec, fps: float | None,
           progress: bool) -> None:
    """Composite TAKE (a recorded take directory or a contraction CSV) with a 2D character into a video.

    Each frame's region states come from its contractions: per region, the muscle (or combination) that
    best explains them, at its level.
    """
    import numpy as np

    from livebridge.character.composite import Compositor
    from livebridge.character.render import video_encoder_problem, write_video
    from livebridge.character.states import ContractionStates
    from livebridge.errors import InputError

    t, contractions, muscle_names = read_contraction_take(take, basis_spec)
    chosen = load_character_spec(character_spec)
    try:
        mapper = ContractionStates(chosen.region_muscles, muscle_names, chosen.region_actuations)
    except InputError as error:  # the character names a muscle the take does not have
        where = character_spec if character_spec == "builtin" else Path(character_spec) / "character.toml"
        raise InputError(f"{error.message} (the take's muscles)", where, "regions") from None
    compositor = Compositor(chosen)
    if fps is None:
        steps = np.diff(t)
        fps = float(1.0 / np.median(steps)) if len(steps) and np.median(steps) > 0 else 30.0
    problem = video_encoder_problem() if out.suffix.lower() in (".mp4", ".mkv", ".mov", ".avi") else None
    if problem is not None:
        click.echo(f"no video encoder ({problem}): writing PNG frames instead", err=True)
    buffer = np.empty_like(compositor.neutral)
    frames = (compositor.composite(mapper(row), buffer) for row in contractions)
    written, count = write_video(frames, out, fps, total=len(contractions), progress=progress)
    click.echo(f"wrote {written}: {count} frames of {chosen.name!r} at {fps:g} fps")

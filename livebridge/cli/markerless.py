"""``livebridge markerless``: train a co-articulation-region model from a take, analyse a take with one."""

from __future__ import annotations

from pathlib import Path

import click

from livebridge.cli._options import FRAMES, ImageFile, InputPath, OutputFile, force_option
from livebridge.cli.markers import load_basis


@click.group("markerless")
def markerless() -> None:
    """Markerless capture: one camera, a bare face (CoArt co-articulation regions, ICA signatures)."""


@markerless.command("train")
@click.argument("take")
@click.option("--out", required=True, type=OutputFile(), help="The model to write (.npz).")
@force_option
@click.option("--report", type=ImageFile(), default=None, help="Also write a PNG of the regions and signatures.")
@click.option("--basis", "basis_spec", type=InputPath(builtins=("builtin",)), default="builtin", show_default=True,
              help="The actuation basis (its muscles; its neutral face guides the pose warp).")
@click.option("--head-rig", "head_rig", type=InputPath(builtins=("none",)), default=None,
              help="The LED head rig (.toml: [leds] name = [x, y, z] mm in the basis's frame), or 'none' "
                   "(head-mounted camera, chin rest). Default: the simulated camera's own rig, else required.")
@click.option("--crop", default=None, help="With --head-rig none: the face's box X,Y,W,H in the image.")
@click.option("--gestures", "gesture_spec", default="isolated", show_default=True,
              help="The gesture list performed, in order: 'isolated' (each muscle), 'simulated' (those and the "
                   "simulator's combined gestures) or a TOML file of [[gesture]] tables.")
@click.option("--method", type=click.Choice(["ica", "pca"]), default="ica", show_default=True,
              help="Signature basis: FastICA (the paper's) or PCA.")
@click.option("--frames", "max_frames", type=FRAMES, default=0, help="Read at most N frames (0: the whole take).")
def train_command(take: str, out: Path, force: bool, report: Path | None, basis_spec, head_rig, crop: str | None,
                  gesture_spec: str, method: str, max_frames: int) -> None:
    """Train a markerless model from TAKE (a camera URL such as sim://face?script=gestures&frames=1440&realtime=0,
    a video file or a folder of images) in which the performer makes each gesture of the list, resting at
    neutral between them."""
    from livebridge.markerless.normalise import HeadRig, Normalisation, default_camera_matrix, load_head_rig
    from livebridge.markerless.report import write_report
    from livebridge.markerless.signatures import require_sklearn
    from livebridge.markerless.takes import TakeFrames, load_gesture_list
    from livebridge.markerless.train import TrainConfig, train

    if method == "ica":
        require_sklearn()
    basis = load_basis(basis_spec)
    prompts = load_gesture_list(gesture_spec, basis.names)
    frames = TakeFrames(take, max_frames or None)
    images = [image for _, image in frames.frames()]
    if not images:
        raise click.UsageError(f"{take}: no frames")
    height, width = images[0].shape[:2]
    camera = frames.camera
    matrix = camera.matrix if camera is not None else default_camera_matrix((width, height))
    distortions = camera.distortions if camera is not None else None
    rig = None
    if head_rig is None:
        video = getattr(frames.source, "video", None)
        if video is None or video.config.head_rig != "leds":
            raise click.BadParameter("give the head rig (.toml) or 'none'", param_hint="--head-rig")
        rig = HeadRig.from_leds(video.head_rig_geometry())
    elif head_rig != "none":
        rig = load_head_rig(head_rig)
    options = {"crop": _crop(crop)} if crop else {}
    if crop and rig is not None:
        raise click.BadParameter("only with --head-rig none", param_hint="--crop")
    norm = Normalisation((width, height), rig, matrix, distortions if distortions is not None else [0.0] * 5,
                         **options)
    mesh = (basis.neutral, basis.triangles) if rig is not None else None
    result = train(images, norm, prompts, basis.names, TrainConfig(method=method), mesh)
    result.model.save(out)
    click.echo(f"trained {len(result.model.regions)} co-articulation regions from {len(images)} frames "
               f"({len(result.gestures)} gestures) -> {out}")
    for region in result.model.regions:
        click.echo(f"  {region.name}: {int(region.mask.sum())} px, {', '.join(region.muscles)}")
    if report is not None:
        write_report(result.model, report)
        click.echo(f"report -> {report}")


@markerless.command("analyse")
@click.argument("take")
@click.option("--model", "model_path", required=True, type=InputPath(), help="A model from `markerless train`.")
@click.option("--out", type=OutputFile(), default=None, help="Write per-frame contractions (CSV).")
@force_option
@click.option("--frames", "max_frames", type=FRAMES, default=0, help="Analyse at most N frames (0: all).")
def analyse_command(take: str, model_path: Path, out: Path | None, force: bool, max_frames: int) -> None:
    """Analyse TAKE with a model: per frame the contractions; prints the mean confidence, the frames with the
    LEDs lost, and the error against the ground truth when the take is simulated."""
    import numpy as np

    from livebridge.markerless.analysis import Analyser
    from livebridge.markerless.model import MarkerlessModel
    from livebridge.markerless.normalise import PoseState, normalise
    from livebridge.markerless.takes import TakeFrames

    model = MarkerlessModel.load(model_path)
    frames = TakeFrames(take, max_frames or None)
    analyser = Analyser(model)
    state, pose = analyser.initial_state(), PoseState()
    rows, confidences, lost, errors = [], [], 0, []
    width, height = model.normalisation.input_size
    for seq, image in frames.frames():
        if image.shape[:2] != (height, width):
            raise click.UsageError(f"{take}: frame {seq} is {image.shape[1]}x{image.shape[0]}, the model expects "
                                   f"{width}x{height}")
        pose, normalised = normalise(image, model.normalisation, pose)
        state, result = analyser.step(state, normalised)
        rows.append([seq, *result.contractions])
        confidences.append(result.mean_confidence)
        lost += result.lost
        truth = getattr(frames.source, "truth", None)
        if truth is not None:
            errors.append(np.abs(result.contractions - truth(seq).contractions))
    if not rows:
        raise click.UsageError(f"{take}: no frames")
    click.echo(f"analysed {len(rows)} frames: mean confidence {np.mean(confidences):.3f}, LEDs lost in {lost}")
    if errors:
        per_muscle = np.mean(errors, axis=0)
        click.echo(f"contraction MAE vs ground truth: {per_muscle.mean():.4f}")
        for name, value in zip(model.muscle_names, per_muscle):
            click.echo(f"  {name}: {value:.4f}")
    if out is not None:
        from livebridge.atomic import write_bytes_atomically

        header = "frame," + ",".join(model.muscle_names)
        lines = [header] + [f"{int(r[0])}," + ",".join(f"{v:.5f}" for v in r[1:]) for r in rows]
        write_bytes_atomically(out, ("\n".join(lines) + "\n").encode(), "contractions CSV")
        click.echo(f"contractions -> {out}")


def _crop(text: str) -> tuple[int, int, int, int]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or min(values[2:]) <= 0 or min(values[:2]) < 0:
        raise click.BadParameter(f"expected X,Y,W,H (whole pixels, W and H > 0), got {text!r}", param_hint="--crop")
    return values

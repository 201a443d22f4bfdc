"""``livebridge calibrate``: print boards, calibrate cameras, show a calibration file."""

from __future__ import annotations

from pathlib import Path

import click

from livebridge.cli._options import (
    MAX_FRAMES,
    CameraURL,
    InputPath,
    Named,
    NewFolder,
    OutputFile,
    force_option,
    unique_names,
)

MAX_PRINT_MM = 2000.0
"""The longest side of a board ``calibrate board`` prints (A0 is 1189 mm)."""


class BoardSpec(click.ParamType):
    """A board spec (``charuco:7x5:40:30:DICT_4X4_50``), read by
    :func:`~livebridge.calibration.boards.parse_board` before any image is read."""

    name = "SPEC"

    def convert(self, value, param, ctx):
        from livebridge.calibration.boards import parse_board
        from livebridge.errors import InputError

        if not isinstance(value, str):
            return value
        try:
            return parse_board(value)
        except InputError as error:
            self.fail(str(error), param, ctx)


@click.group()
def calibrate() -> None:
    """Multi-camera calibration with a chessboard or ChArUco board."""


@calibrate.command("board")
@click.argument("board", metavar="SPEC", type=BoardSpec())
@click.option("--out", "out", required=True, type=OutputFile(), help="Output file, .png or .pdf.")
@force_option
@click.option("--dpi", type=click.IntRange(72, 1200), default=300, show_default=True, help="Print resolution.")
def board_command(board, out: Path, force: bool, dpi: int) -> None:
    """Write a print-ready board for SPEC at exact physical size, with a scale bar.

    SPEC is 'chessboard:COLSxROWS:SQUARE_MM' (inner corners) or
    'charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT[:legacy]' (squares).
    """
    from livebridge.calibration.printout import write_board

    if max(board.size_mm) > MAX_PRINT_MM:  # the page is drawn in memory at --dpi: a huge one never ends
        raise click.BadParameter(f"a {board.size_mm[0]:g} x {board.size_mm[1]:g} mm board does not print (at most "
                                 f"{MAX_PRINT_MM:g} mm a side)", param_hint="SPEC")
    width, height = write_board(board, out, dpi)
    click.echo(f"wrote {out}: page {width:g} x {height:g} mm; print at 100% and check the scale bar")


@calibrate.command("run")
@click.option("--images", multiple=True, type=Named(click.STRING, "DIR"),
              help="A camera's folder of images (or a glob such as 'dir/left*.jpg'); repeat per camera.")
@click.option("--videos", multiple=True, type=Named(InputPath(), "FILE"),
              help="A camera's video file; repeat per camera.")
@click.option("--sources", multiple=True, type=Named(CameraURL(), "URL"),
              help="A live camera source URL (e.g. v4l2:///dev/video0, or a camera node's "
                   "node://HOST:PORT?camera=ID: the node detects the board); repeat per camera. Hold the board still.")
@click.option("--board", "board", required=True, type=BoardSpec(),
              help="Board spec, e.g. 'charuco:7x5:40:30:DICT_4X4_50'.")
@click.option("--out", "out", required=True, type=OutputFile(), help="Calibration file to write (TOML).")
@force_option
@click.option("--fisheye", is_flag=True, help="Fisheye lens model (k1..k4) instead of pinhole with 5 terms.")
@click.option("--up", type=click.Choice(["y", "z"]), default="y", show_default=True, help="World axis that is up.")
@click.option("--origin-view", type=click.IntRange(0, MAX_FRAMES), default=None,
              help="Index of the view whose board defines the world frame (default: the best-seen view).")
@click.option("--board-pose", type=click.Choice(["upright", "flat"]), default="upright", show_default=True,
              help="How the board stands in the origin view: upright facing the cameras, or flat printed side up.")
@click.option("--every", type=click.IntRange(1, 100_000), default=10, show_default=True,
              help="Videos/sources: use every N-th frame.")
@click.option("--frames", type=click.IntRange(1, 100_000), default=300, show_default=True,
              help="Sources: frame sets to grab.")
@click.option("--report", "report_dir", type=NewFolder(exist_ok=True), default=None,
              help="Folder for the report (default: next to --out, named after it).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def run_command(images, videos, sources, board, out, force, fisheye, up, origin_view, board_pose, every, frames,
                report_dir, quiet) -> None:
    """Calibrate cameras from board images, videos or live sources.

    Images in a folder pair across cameras by file name (identical names, else the
    last number in the name, else sorted order); videos pair by frame index.
    """
    chosen = [name for name, given in (("--images", images), ("--videos", videos), ("--sources", sources)) if given]
    if len(chosen) != 1:
        raise click.UsageError("give exactly one of --images, --videos or --sources (one NAME=... per camera)")
    folder = report_dir or out.with_name(out.stem + "_report")
    if report_dir is None and folder.exists() and not folder.is_dir():
        raise click.BadParameter(f"the report folder {folder} is a file; name another with --report",
                                 param_hint="--out")
    named = unique_names(images or videos or sources, chosen[0])
    _run(chosen[0], named, board, out, fisheye, up, origin_view, board_pose, every, frames, folder, quiet)


def _run(kind, named, board, out, fisheye, up, origin_view, board_pose, every, frames, folder, quiet) -> None:
    from livebridge.calibration.calibfile import save_calibration
    from livebridge.calibration.detect import detect_frames, detect_images, read_videos
    from livebridge.calibration.report import summary, write_report
    from livebridge.calibration.run import calibrate as run_calibration

    progress = not quiet
    if kind == "--images":
        detections = detect_images(board, named, progress=progress)
    elif kind == "--videos":
        frame_sets, total = read_videos(named)
        detections = detect_frames(board, list(named), frame_sets, progress, total, every=every)
    else:
        detections = detect_frames(board, list(named), _source_frames(named, frames, board), progress, frames,
                                   every=every)
    found = detections.counts() >= board.min_corners
    click.echo("board found in: " + ", ".join(f"{n} {int(k)}/{detections.n_views}"
                                               for n, k in zip(detections.camera_names, found.sum(axis=1))), err=True)
    result = run_calibration(detections, board, fisheye=fisheye, up=up, origin_view=origin_view,
                             board_pose=board_pose, log=lambda line: click.echo(line, err=True))
    save_calibration(out, result.group, result.metadata())
    write_report(result, folder)
    click.echo(summary(result))
    click.echo(f"wrote {out} and report in {folder}")


def _source_frames(named: dict[str, str], n_frames: int, board):
    """Frame sets from live sources (``livebridge.devices.registry``): one frame per camera, read in turn.

    Every source is told the board (``CameraSource.detect_board_with``); one that can detect it where it
    films (a camera node) does, and gives the corners it found
    (:class:`~livebridge.calibration.detect.FoundCorners`) in place of its image. Frames are matched by read
    order, not by hardware sync, so hold the board still for a moment in each pose.
    """
    from livebridge.devices.registry import open_camera, stop_sources
    from livebridge.errors import InputError

    opened = []
    try:
        for url in named.values():
            opened.append(open_camera(url))
        for source in opened:
            source.detect_board_with(board)  # a camera node detects it where it films
            source.start()
        blind = dict.fromkeys(named, 0)  # frames in a row with neither corners nor an image, per camera
        for _ in range(n_frames):
            frame_set = []
            for name, source in zip(named, opened):
                view = _board_view(_next_frame(source, named[name], name), source)
                blind[name] = blind[name] + 1 if view is _BLIND else 0
                if blind[name] > MAX_BLIND_FRAMES:
                    raise InputError("this camera sends neither the board's corners nor its images (a camera "
                                     "node that does not detect boards): add images=full to its URL for "
                                     "calibration", named[name], f"--sources {name}")
                frame_set.append(None if view is _BLIND else view)
            yield frame_set
    finally:
        stop_sources(opened)


MAX_BLIND_FRAMES = 30
"""Frames in a row a camera may send with neither board corners nor its image (a camera node's first frames,
sent before it heard of the board) before calibration refuses it."""
_BLIND = object()


def _board_view(frame, source):
    """What :func:`~livebridge.calibration.detect.detect_frames` takes of a frame: the corners found where it
    was taken, else its image; None for no frame, ``_BLIND`` for one that carries neither."""
    from livebridge.calibration.detect import FoundCorners

    if frame is None:
        return None
    if frame.board_corners is not None:
        return FoundCorners(frame.board_corners, source.capabilities.size)
    if frame.image.size == 0 or not source.capabilities.images:
        return _BLIND
    return frame.image


UNPACED_WAIT_S = 60.0


def _next_frame(source, url: str, name: str):
    """The source's next frame; None when a live camera gave none within 2 s. An unpaced source (a replay, a
    simulated board, a camera node serving one) delivers every frame however long it takes, so its frame sets
    stay paired: it is waited for (up to :data:`UNPACED_WAIT_S`)."""
    from livebridge.errors import InputError

    frame = source.read(timeout=2.0 if source.realtime else UNPACED_WAIT_S)
    if frame is None and (source.ended or not source.realtime):
        why = source.error or "ended" if source.ended else f"no frame for {UNPACED_WAIT_S:g} s"
        raise InputError(f"camera stopped delivering frames ({why})", url, f"--sources {name}")
    return frame


@calibrate.command("show")
@click.argument("path", type=InputPath())
def show_command(path: Path) -> None:
    """Print the cameras of a calibration file (ours or aniposelib's)."""
    from livebridge.calibration.calibfile import load_calibration, load_metadata

    group = load_calibration(path)
    metadata = load_metadata(path)
    for camera in group.cameras:
        rms = metadata.get("rms_px", {}).get(camera.name)
        click.echo(f"{camera.name:12s} {camera.size[0]}x{camera.size[1]} f={camera.matrix[0, 0]:.1f} "
                   f"centre=({', '.join(f'{v:.1f}' for v in camera.center)}) mm"
                   + (f" RMS {rms:.3f} px" if rms is not None else ""))
    if "world_frame" in metadata:
        click.echo(f"world frame: {metadata['world_frame']}")

"""Offline playback: a take's frames composited into a video (PyAV, H.264) or a PNG sequence.

A video needs the optional extra ``video`` (PyAV with an H.264 encoder); without it, or for an output
that is not a video file, the frames are written as a numbered PNG sequence in a folder.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from livebridge.character.definition import write_image

VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov", ".avi")
CODEC = "libx264"


def video_encoder_problem() -> str | None:
    """Why no H.264 video can be written here (PyAV missing, no encoder); None when it can."""
    try:
        import av
    except ImportError:
        return "PyAV is not installed (pip install 'livebridge[video]')"
    try:
        av.codec.Codec(CODEC, "w")
    except ValueError as error:  # av.codec.codec.UnknownCodecError: this FFmpeg build lacks the encoder
        return f"PyAV has no {CODEC} encoder ({type(error).__name__})"
    return None


def png_folder(out: Path) -> Path:
    """The folder a PNG sequence for ``out`` goes to: ``out`` itself, or ``out`` without its video suffix."""
    return out.with_suffix("") if out.suffix.lower() in VIDEO_SUFFIXES else out


def _to_rgb8(frame: np.ndarray) -> np.ndarray:
    rgb = np.repeat(frame, 3, axis=2) if frame.shape[2] == 1 else frame
    return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)


def write_video(frames: Iterable[np.ndarray], out: Path, fps: float, total: int | None = None,
                progress: bool = True) -> tuple[Path, int]:
    """Write composited frames ``(height, width, n_channels)`` float [0, 1] to ``out``.

    A video file (``.mp4``, ``.mkv``, ``.mov``, ``.avi``) is H.264 (yuv420p; an odd width or height is
    padded by one pixel) when PyAV can encode it, otherwise (and for any other ``out``) a PNG sequence
    ``frame_000000.png ...`` in :func:`png_folder`. Returns the path written and the number of frames.
    """
    from tqdm import tqdm

    out = Path(out)
    bar = tqdm(frames, total=total, unit="frame", disable=not progress, leave=False)
    if out.suffix.lower() in VIDEO_SUFFIXES and video_encoder_problem() is None:
        return out, _encode(bar, out, fps)
    folder = png_folder(out)
    folder.mkdir(parents=True, exist_ok=True)
    count = 0
    for count, frame in enumerate(bar, start=1):
        write_image(folder / f"frame_{count - 1:06d}.png", frame)
    return folder, count


def _encode(frames: Iterable[np.ndarray], out: Path, fps: float) -> int:
    from fractions import Fraction

    import av

    count = 0
    with av.open(str(out), "w") as container:
        stream = None
        for frame in frames:
            rgb = _to_rgb8(frame)
            if stream is None:
                stream = container.add_stream(CODEC, rate=Fraction(fps).limit_denominator(1000))
                stream.width, stream.height = rgb.shape[1] + rgb.shape[1] % 2, rgb.shape[0] + rgb.shape[0] % 2
                stream.pix_fmt = "yuv420p"
            if rgb.shape[:2] != (stream.height, stream.width):
                rgb = np.pad(rgb, ((0, stream.height - rgb.shape[0]), (0, stream.width - rgb.shape[1]), (0, 0)),
                             mode="edge")
            for packet in stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                container.mux(packet)
            count += 1
        if stream is not None:
            for packet in stream.encode():
                container.mux(packet)
    return count

"""Reading a markerless take: a camera URL (``sim://face?...&frames=N``, ``replay://...``), a video file, or a
folder of images; and gesture lists (TOML)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.markerless.train import GesturePrompt, isolated_prompts

IMAGE_SUFFIXES = (".png", ".pgm", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class TakeFrames:
    """The frames of a take, read once in order (``frames()``), with what the source knows about itself.

    Attributes
    ----------
    camera : Camera or None
        The source's own calibration, when it has one (a simulated camera, a recorded take).
    source : object or None
        The camera source for a URL (a simulator's has ``truth(seq)``).
    """

    def __init__(self, spec: str, max_frames: int | None = None):
        self.spec, self.max_frames = str(spec), max_frames
        self.camera = None
        self.source = None
        if "://" in self.spec:
            from livebridge.devices.registry import open_cameras

            sources = open_cameras(self.spec)
            if len(sources) != 1:
                raise InputError(f"a markerless take is filmed by one camera, the URL opened {len(sources)}",
                                 self.spec)
            self.source = sources[0]
            self.camera = getattr(self.source, "calibration", None)
        elif not Path(self.spec).exists():
            raise InputError("no such file or folder", self.spec)

    def frames(self) -> Iterator[tuple[int, np.ndarray]]:
        """(frame number, grey image (H, W) uint8) in order."""
        if self.source is not None:
            yield from self._from_source()
        elif Path(self.spec).is_dir():
            yield from self._from_folder()
        else:
            yield from self._from_video()

    def _limit(self, count: int) -> bool:
        return self.max_frames is not None and count >= self.max_frames

    def _from_source(self):
        self.source.start()
        try:
            count = 0
            while not self._limit(count):
                frame = self.source.read(timeout=5.0)
                if frame is None:
                    return
                yield frame.seq, _grey(frame.image)
                count += 1
        finally:
            self.source.stop()

    def _from_folder(self):
        import cv2

        files = sorted(p for p in Path(self.spec).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in the folder", self.spec)
        for k, path in enumerate(files):
            if self._limit(k):
                return
            image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise InputError("not a readable image", path)
            yield k, image

    def _from_video(self):
        import cv2

        capture = cv2.VideoCapture(self.spec)
        if not capture.isOpened():
            raise InputError("not a video file OpenCV can read", self.spec)
        try:
            k = 0
            while not self._limit(k):
                ok, image = capture.read()
                if not ok:
                    if k == 0:
                        raise InputError("the video has no frames OpenCV can decode", self.spec)
                    return
                yield k, _grey(image)
                k += 1
        finally:
            capture.release()


def _grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        import cv2

        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image


def load_gesture_list(spec: str | Path, muscle_names) -> tuple[GesturePrompt, ...]:
    """A gesture list: ``"isolated"`` (each muscle in turn), ``"simulated"`` (those, then the face-video
    simulator's combined gestures), or a TOML file of ``[[gesture]]`` tables with ``name`` and ``muscles``
    (``{muscle = level at full actuation}``), in the order performed."""
    muscle_names = tuple(muscle_names)
    if spec == "isolated":
        return isolated_prompts(muscle_names)
    if spec == "simulated":
        from livebridge.markerless.train import combination_prompts
        from livebridge.simulators.performer import COMBINED_GESTURES

        combined = {name: levels for name, levels in COMBINED_GESTURES.items()
                    if all(m in muscle_names for m in levels)}
        return isolated_prompts(muscle_names) + combination_prompts(combined)
    from livebridge.tomlio import load_toml

    table = load_toml(spec)
    entries = table.get("gesture")
    if not isinstance(entries, list) or not entries:
        raise InputError("expected [[gesture]] tables", spec, "gesture")
    prompts = []
    for k, entry in enumerate(entries):
        field = f"gesture[{k}]"
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str) or not entry["name"]:
            raise InputError("each gesture needs a name", spec, f"{field}.name")
        muscles = entry.get("muscles")
        if not isinstance(muscles, dict) or not muscles:
            raise InputError("expected a table {muscle = level}", spec, f"{field}.muscles")
        for muscle, level in muscles.items():
            if muscle not in muscle_names:
                raise InputError(f"unknown muscle {muscle!r}; the basis has {', '.join(muscle_names)}", spec,
                                 f"{field}.muscles.{muscle}")
            if isinstance(level, bool) or not isinstance(level, (int, float)) or not 0 < level <= 1:
                raise InputError(f"level must be a number in (0, 1], got {level!r}", spec,
                                 f"{field}.muscles.{muscle}")
        prompts.append(GesturePrompt(entry["name"], {m: float(v) for m, v in muscles.items()}))
    names = [p.name for p in prompts]
    if len(set(names)) != len(names):
        raise InputError("gesture names repeat", spec, "gesture")
    return tuple(prompts)

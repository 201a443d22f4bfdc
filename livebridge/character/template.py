"""Guide sheets for artists: what to draw for a character driven by a markerless model.

For each CR and each state of each of its muscles, a guide image (the training frame that defines the
state, the CR's mask outlined on it, and the box a sample at the performer's proportions would fill) and one
line in ``samples.csv``, the list of samples to draw; plus ``overview.png`` (the neutral face with every CR),
the CR masks (``masks/REGION.png``, in the face's image space) and a ``character.toml`` skeleton that names
every sample to draw, places the masks with a ``[warp]`` (identity until the artist moves its
``character_points`` onto the character) and loads as soon as the samples and a ``neutral.png`` exist.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import cv2
import numpy as np

from livebridge.atomic import write_bytes_atomically
from livebridge.character.definition import FORMAT, VERSION, write_image
from livebridge.character.rewrite import intensity_scale
from livebridge.tomlio import save_toml

OUTLINE = (1.0, 0.35, 0.1)
BOX = (0.2, 0.8, 1.0)


def _file_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def _guide(frame: np.ndarray, masks: list[np.ndarray], box: tuple[int, int, int, int] | None,
           label: str) -> np.ndarray:
    """A grey frame in colour with ``masks`` outlined, ``box`` drawn and ``label`` written, (H, W, 3) float."""
    grey = np.clip(np.rint(np.asarray(frame, np.float32) * 255), 0, 255).astype(np.uint8)
    image = np.repeat(grey[..., None], 3, axis=2)
    outline, box_colour = (tuple(int(255 * v) for v in colour) for colour in (OUTLINE, BOX))
    if box is not None:  # under the outline, which it touches
        x, y, w, h = box
        cv2.rectangle(image, (x, y), (x + w - 1, y + h - 1), box_colour, 1)
    for mask in masks:
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(image, contours, -1, outline, 1)
    scale = max(0.3, image.shape[1] / 900)
    cv2.putText(image, label, (4, int(16 * scale / 0.4)), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 50), 1,
                cv2.LINE_AA)
    return image.astype(np.float32) / 255.0


def write_template(model, out: Path) -> tuple[Path, int]:
    """Write the guide sheets for ``model`` (a MarkerlessModel) into the new folder ``out``.

    Returns ``(path of samples.csv, number of samples to draw)``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scale = intensity_scale(model)
    width, height = model.image_size
    neutral = np.asarray(model.neutral_image, np.float32) / scale
    write_image(out / "overview.png", _guide(neutral, [cr.mask for cr in model.regions], None,
                                             f"{len(model.regions)} regions"))
    rows, regions = [], []
    for cr in model.regions:
        region_file = _file_name(cr.name)
        mask_file = f"masks/{region_file}.png"
        write_image(out / mask_file, cr.mask.astype(np.float32))
        ys, xs = np.nonzero(cr.mask)
        box = (int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1))
        samples = []
        for muscle, n_states in zip(cr.muscles, cr.n_states):
            n_samples = max(n_states - 1, 1)
            for k in range(1, n_samples + 1):
                frame = model.state_frame(cr.name, muscle, k if n_states > 1 else 0) / scale
                stem = f"{region_file}/{_file_name(muscle)}_{k}"
                guide = f"guides/{stem}.png"
                label = f"{cr.name}: {muscle} {k}/{n_samples}"
                write_image(out / guide, _guide(frame, [cr.mask], box, label))
                sample = f"samples/{stem}.png"
                samples.append({"muscle": muscle, "state": k, "image": sample, "at": [box[0], box[1]]})
                rows.append([cr.name, muscle, k, n_samples, f"{k / n_samples:.3f}", guide, sample, box[0], box[1],
                             box[2], box[3]])
        regions.append({"name": cr.name, "muscles": list(cr.muscles),
                        "states": [max(n - 1, 1) for n in cr.n_states], "mask": mask_file, "mask_space": "face",
                        "samples": samples})
    corners = [[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]]
    save_toml(out / "character.toml", {
        "format": FORMAT, "version": VERSION, "name": "new character", "neutral": "neutral.png",
        "feather_px": 10.0,
        "warp": {"face_size": [width, height], "face_points": corners, "character_points": corners},
        "regions": regions})
    table = io.StringIO()
    writer = csv.writer(table, lineterminator="\n")
    writer.writerow(["region", "muscle", "state", "of", "level", "guide", "draw", "x", "y", "width", "height"])
    writer.writerows(rows)
    listing = out / "samples.csv"
    write_bytes_atomically(listing, table.getvalue().encode(), "sample list")
    return listing, len(rows)

"""The live 2D character: the render client's 2D view, fed once with the samples and then per frame with
the CR states (the page composites, as :mod:`~livebridge.character.composite` does).

Wire protocol (after the render server's own init and mesh messages; little-endian)
------------------------------------------------------------------------------------
1. text JSON ``{"type": "character", "name", "width", "height", "regions": [{"name", "muscles",
   "counts" (samples per muscle), "rect": [x, y, w, h], "fade_regions": [earlier region indices]}]}``;
2. binary *character samples*: ``uint32[4] = (3, width, height, n_regions)``, the neutral image ``uint8
   (height, width, 4)`` RGBA, then per region its sample layers ``uint8 (n_samples, h, w, 4)`` (colour
   premultiplied by the alpha, alpha last; samples in muscle order, states 1..K) and its cross-fade weights
   ``uint8 (n_fades, h, w)`` (255 = 1), padded with zeros to a multiple of 4 bytes;
3. per frame, binary *character states*: ``uint32[3] = (4, seq, n_regions)``, ``int32 muscle (n_regions,)``
   (-1: neutral), ``float32 level (n_regions,)``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np

from livebridge.character.composite import Compositor
from livebridge.character.definition import Character
from livebridge.character.states import ContractionStates, CRStates, states_from_regions

SAMPLES_KIND = 3
STATES_KIND = 4


def _u8(values: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(values * 255.0), 0, 255).astype(np.uint8)


def _rgba(image: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """float (h, w, 1 or 3) [+ alpha (h, w)] -> float (h, w, 4) RGBA."""
    rgb = np.repeat(image, 3, axis=-1) if image.shape[-1] == 1 else image
    a = np.ones(image.shape[:-1], np.float32) if alpha is None else alpha
    return np.concatenate([rgb, a[..., None]], axis=-1)


def encode_character(compositor: Compositor) -> tuple[str, bytes]:
    """The character's init text and samples message (layout in the module docstring)."""
    character = compositor.character
    width, height = character.size
    regions, parts = [], [np.array([SAMPLES_KIND, width, height, len(compositor.tables)], "<u4").tobytes(),
                          _u8(_rgba(compositor.neutral)).tobytes()]
    for region, table in zip(character.regions, compositor.tables):
        layers = table.layers[1:]  # layer 0 is the neutral state (nothing drawn)
        h, w = layers.shape[1:3]
        regions.append({"name": region.name, "muscles": list(region.muscles), "counts": list(table.counts),
                        "rect": [table.x, table.y, w, h], "fade_regions": table.fade_regions.tolist()})
        parts.append(_u8(_rgba(layers[..., :-1], layers[..., -1])).tobytes())
        fades = _u8(table.fades).tobytes()
        parts.append(fades + bytes(-len(fades) % 4))
    text = json.dumps({"type": "character", "name": character.name, "width": width, "height": height,
                       "regions": regions})
    return text, b"".join(parts)


def encode_states(seq: int, states: CRStates) -> bytes:
    """The per-frame states message (layout in the module docstring)."""
    muscle = np.asarray(states.muscle, "<i4")
    header = np.array([STATES_KIND, seq & 0xFFFFFFFF, len(muscle)], "<u4")
    return header.tobytes() + muscle.tobytes() + np.asarray(states.level, "<f4").tobytes()


class CharacterOutput:
    """An :class:`~livebridge.output.Output` (``describe``, ``send(frame)``, ``close``) that drives a 2D character
    from the pipeline's solved frames.

    Each frame's CR states come from its per-region markerless states (``frame.regions``) when the
    character has the model's regions, otherwise from its contractions
    (:class:`~livebridge.character.states.ContractionStates`); they go to the render client's 2D view when a
    render server is given (:meth:`attach`), and are kept as :attr:`states`; :meth:`image` composites them.

    Parameters
    ----------
    character : Character
    muscle_names : sequence of str
        The basis muscles, in the order of the frames' contractions.
    server : RenderServer, optional
        Its 2D view shows the character (attach before clients connect: the samples go to each client as it
        connects).
    """

    def __init__(self, character: Character, muscle_names: Sequence[str], server=None):
        self.character = character
        self.compositor = Compositor(character)
        self._from_contractions = ContractionStates(character.region_muscles, muscle_names,
                                                    character.region_actuations)
        self.states = CRStates.neutral(len(character.regions))
        self.frames = 0
        self.server = None
        if server is not None:
            self.attach(server)

    def attach(self, server) -> None:
        """Show the character in ``server``'s 2D view."""
        server.show_character(*encode_character(self.compositor))
        self.server = server

    def describe(self) -> str:
        where = "the render page's 2D view" if self.server is not None else "nowhere (no render page)"
        return f"2D character {self.character.name!r} ({len(self.character.regions)} regions) -> {where}"

    def states_of(self, frame) -> CRStates:
        """The CR states of a solved frame (anything with ``contractions``, maybe ``regions``)."""
        regions = getattr(frame, "regions", None)
        if regions is not None:
            states = states_from_regions(self.character.region_names, regions)
            if states is not None:
                return states
        return self._from_contractions(frame.contractions)

    def send(self, frame) -> None:
        self.states = self.states_of(frame)
        self.frames += 1
        if self.server is not None:
            self.server.publish_character(encode_states(frame.seq, self.states))

    def image(self) -> np.ndarray:
        """The character for the latest states, shape (height, width, n_channels) float32."""
        return self.compositor.composite(self.states)

    def close(self) -> None:
        self.server = None

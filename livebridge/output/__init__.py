"""Outputs of the live pipeline: the render client (:mod:`.render_server`) and every other consumer of
solved frames (:mod:`.vmc`, ...), each an :class:`Output`."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from livebridge.runtime.frame import SolvedFrame


class Output(Protocol):
    """A consumer of solved frames, run on the pipeline's outputs thread (it must never block it)."""

    def describe(self) -> str:
        """One line for the start-up banner: where the frames go."""

    def send(self, frame: SolvedFrame) -> None:
        """Send one solved frame."""

    def close(self) -> None:
        """Release the output (the pipeline has stopped)."""

"""Print-ready board files (PNG or PDF) at exact physical size, with a scale bar to check the print."""

from __future__ import annotations

import math
from pathlib import Path

from livebridge.calibration.boards import Board
from livebridge.errors import InputError

MARGIN_MM = 10.0
FOOTER_MM = 22.0


def write_board(board: Board, path: str | Path, dpi: int = 300) -> tuple[float, float]:
    """Write the board to ``path`` (``.png`` or ``.pdf``) at 1:1 physical scale.

    The page is the board's grid plus a white quiet zone of half a square, a 10 mm page margin
    and a footer with a scale bar (1 mm ticks under 20 mm, else 10 mm ticks) and the spec.

    Returns
    -------
    (width_mm, height_mm) of the page.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    path = Path(path)
    if path.suffix.lower() not in (".png", ".pdf"):
        raise InputError("the board file must end in .png or .pdf", path, "--out")
    if dpi < 72:
        raise InputError(f"dpi {dpi} is too low to print a board", field="--dpi")
    grid_w, grid_h = board.size_mm
    quiet = 0.5 * board.square_mm
    page_w = grid_w + 2 * quiet + 2 * MARGIN_MM
    page_w = max(page_w, 60.0 + 2 * MARGIN_MM)
    page_h = grid_h + 2 * quiet + 2 * MARGIN_MM + FOOTER_MM
    px_per_square = max(8, math.ceil(board.square_mm / 25.4 * dpi))
    image = board.image(px_per_square, margin_squares=0.5)

    fig = plt.figure(figsize=(page_w / 25.4, page_h / 25.4), dpi=dpi)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, page_w)
    ax.set_ylim(page_h, 0)  # mm, y down like the board frame
    ax.axis("off")
    left = (page_w - grid_w - 2 * quiet) / 2
    top = MARGIN_MM
    ax.imshow(image, cmap="gray", vmin=0, vmax=255, interpolation="nearest",
              extent=(left, left + grid_w + 2 * quiet, top + grid_h + 2 * quiet, top))
    # scale bar
    bar = next(length for length in (200, 100, 50, 20, 10) if length <= page_w - 2 * MARGIN_MM)
    tick = 1 if bar <= 20 else 10
    y = top + grid_h + 2 * quiet + 7
    x0 = (page_w - bar) / 2
    ax.add_patch(Rectangle((x0, y), bar, 1.2, color="black", lw=0))
    for i in range(bar // tick + 1):
        height = 3.0 if i in (0, bar // tick) else 1.8
        ax.add_patch(Rectangle((x0 + i * tick - 0.15, y - height), 0.3, height, color="black", lw=0))
    ax.text(page_w / 2, y + 4.5, f"this bar must measure {bar} mm - print at 100% (no 'fit to page')",
            ha="center", va="top", fontsize=6)
    ax.text(page_w / 2, y + 8.5, f"livebridge board  {board.spec}  ({grid_w:g} x {grid_h:g} mm grid)",
            ha="center", va="top", fontsize=6, family="monospace")
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return page_w, page_h

"""A PNG report of a markerless model: the CR masks on the neutral face, and each CR's signature sets."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livebridge.markerless.model import MarkerlessModel


def write_report(model: MarkerlessModel, path: str | Path) -> None:
    """Write the report: panel 1 the canonical neutral face with every CR's mask in its own colour and name;
    then per CR its signatures (rows: each (pseudo-)muscle's states, neutral to full; columns: signature
    components), muscles separated by lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    regions = model.regions
    n_panels = 1 + len(regions)
    columns = min(4, n_panels)
    rows = int(np.ceil(n_panels / columns))
    figure, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.4 * rows), squeeze=False)
    colours = plt.get_cmap("tab20")(np.arange(max(1, len(regions))) % 20)
    overlay = np.repeat((model.neutral_image / max(1.0, float(model.neutral_image.max())))[..., None], 3, axis=2)
    first = axes[0, 0]
    for region, colour in zip(regions, colours):
        overlay[region.mask] = 0.45 * overlay[region.mask] + 0.55 * colour[:3]
    first.imshow(overlay)
    for region in regions:
        ys, xs = np.nonzero(region.mask)
        first.text(xs.mean(), ys.mean(), region.name, fontsize=7, ha="center", va="center", color="white",
                   bbox={"facecolor": "black", "alpha": 0.5, "pad": 1, "linewidth": 0})
    first.set_title(f"{len(regions)} co-articulation regions ({model.method.upper()})", fontsize=9)
    for k, region in enumerate(regions, start=1):
        axis = axes[k // columns, k % columns]
        table = np.concatenate(region.signatures, axis=0)
        axis.imshow(table, aspect="auto", cmap="coolwarm", vmin=-1, vmax=1, interpolation="nearest")
        edges = np.cumsum(region.n_states)[:-1] - 0.5
        for edge in edges:
            axis.axhline(edge, color="black", linewidth=0.6)
        centres = np.cumsum(region.n_states) - np.asarray(region.n_states) / 2 - 0.5
        axis.set_yticks(centres, [m[:22] for m in region.muscles], fontsize=5)
        axis.set_xticks([])
        axis.set_title(f"{region.name}: signatures ({table.shape[1]} components)", fontsize=8)
    for k in range(n_panels, rows * columns):
        axes[k // columns, k % columns].axis("off")
    first.axis("off")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)

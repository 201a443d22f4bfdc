"""``livebridge basis show``: render a basis (neutral face and each element) to an image."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from livebridge.cli._options import FiniteFloat, ImageFile, InputPath, force_option
from livebridge.cli.markers import BASIS_TYPE, load_basis
from livebridge.face import SHIPPED_MARKER_SETS


def _view(vertices: np.ndarray, yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """Rotate ``vertices (..., 3)`` into the view frame (camera looks along -z): yaw about y, then pitch about x."""
    yaw, pitch = np.deg2rad(yaw_deg), np.deg2rad(pitch_deg)
    rot_y = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    rot_x = np.array([[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]])
    return vertices @ (rot_x @ rot_y).T


_LIGHT = np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0])


def _draw_mesh(ax, vertices, triangles, colours, light=_LIGHT):
    """Painter's-algorithm orthographic render of the triangles that face the viewer."""
    from matplotlib.collections import PolyCollection

    from livebridge.face.meshio import triangle_normals

    corners = vertices[triangles]  # (T, 3, 3)
    normals = triangle_normals(vertices, triangles)
    visible = normals[:, 2] > 0
    order = np.flatnonzero(visible)[np.argsort(corners[visible, :, 2].mean(axis=1))]
    shade = np.clip(normals[order] @ light, 0, 1)[:, None]
    face = colours[order, :3] * (0.25 + 0.75 * shade)
    ax.add_collection(PolyCollection(corners[order, :, :2], facecolors=np.clip(face, 0, 1), edgecolors="none",
                                     antialiased=False))


def render_basis(basis, path: str | Path, markers=None, yaw_deg: float = 15.0, pitch_deg: float = 5.0,
                 dpi: int = 90, arrows: int = 70, arrow_gain: float = 2.0, muscles=None, panel_inches: float = 3.0,
                 crop_y: tuple[float, float] | None = None) -> None:
    """Render the neutral face and each element into one image, one panel each.

    The neutral panel is shaded skin (with the markers, if given: face markers white, head markers
    blue); each element's panel shows the face fully contracted, coloured by displacement magnitude
    (mm, colour bar per panel) with arrows along the displacement (seen from the same view).

    Parameters
    ----------
    basis : Basis
    path : str or Path
        Image file (format from the suffix, e.g. ``.png``).
    markers : MarkerSet, optional
    yaw_deg, pitch_deg : float
        View direction: the face turned by ``yaw_deg`` about the vertical axis, ``pitch_deg`` about x.
    arrows : int
        Number of displacement arrows per panel (sampled with probability growing with displacement).
    arrow_gain : float
        Arrows are drawn this many times longer than the displacement.
    muscles : sequence of str, optional
        Only these elements (default: all).
    panel_inches : float
    crop_y : (float, float), optional
        Only show this range of heights (model y, mm) of the neutral face.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import cm

    shown = list(range(basis.n_muscles)) if muscles is None else [basis.index(name) for name in muscles]
    n_panels = len(shown) + 1
    n_cols = min(6, n_panels)
    n_rows = -(-n_panels // n_cols)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(panel_inches * n_cols, 1.1 * panel_inches * n_rows),
                             squeeze=False)
    neutral_view = _view(basis.neutral, yaw_deg, pitch_deg)
    framed = neutral_view
    if crop_y is not None:
        framed = neutral_view[(basis.neutral[:, 1] >= crop_y[0]) & (basis.neutral[:, 1] <= crop_y[1])]
    low, high = framed.min(axis=0), framed.max(axis=0)
    pad = 0.04 * (high - low)
    skin = np.tile([0.93, 0.80, 0.70, 1.0], (len(basis.triangles), 1))
    rng = np.random.default_rng(0)
    for panel, ax in enumerate(axes.ravel()):
        ax.set_axis_off()
        if panel >= n_panels:
            continue
        ax.set_xlim(low[0] - pad[0], high[0] + pad[0])
        ax.set_ylim(low[1] - pad[1], high[1] + pad[1])
        ax.set_aspect("equal")
        if panel == 0:
            _draw_mesh(ax, neutral_view, basis.triangles, skin)
            title = f"neutral ({basis.n_vertices} vertices)"
            if markers is not None:
                points = _view(markers.neutral_positions(basis), yaw_deg, pitch_deg)
                face = markers.face_mask
                ax.scatter(points[face, 0], points[face, 1], s=7, c="white", edgecolors="black", linewidths=0.4,
                           zorder=3)
                ax.scatter(points[~face, 0], points[~face, 1], s=12, c="tab:blue", edgecolors="black",
                           linewidths=0.4, zorder=3)
                title += f"\n{int(face.sum())} face + {int((~face).sum())} head markers"
            ax.set_title(title, fontsize=8)
            continue
        muscle = basis.muscles[shown[panel - 1]]
        element = basis.elements[shown[panel - 1]]
        magnitude = np.linalg.norm(element, axis=1)
        level = magnitude[basis.triangles].mean(axis=1) / max(magnitude.max(), 1e-9)  # 0..1 per triangle
        colour = skin.copy()
        heat = cm.inferno_r(0.15 + 0.7 * level)
        colour[:, :3] = (1 - level[:, None] ** 0.6) * skin[:, :3] + level[:, None] ** 0.6 * heat[:, :3]
        deformed = _view(basis.neutral + element, yaw_deg, pitch_deg)
        _draw_mesh(ax, deformed, basis.triangles, colour)
        # arrows at moving, front-facing vertices, sampled with probability ~ magnitude
        start = neutral_view
        delta = _view(element, yaw_deg, pitch_deg)
        moving = np.flatnonzero((magnitude > 0.15 * magnitude.max()) & (start[:, 2] > np.median(start[:, 2])))
        if moving.size:
            pick = rng.choice(moving, size=min(arrows, moving.size), replace=False,
                              p=magnitude[moving] / magnitude[moving].sum())
            ax.quiver(start[pick, 0], start[pick, 1], arrow_gain * delta[pick, 0], arrow_gain * delta[pick, 1],
                      angles="xy",
                      scale_units="xy", scale=1.0, width=0.007, headwidth=3.5, color="tab:cyan",
                      edgecolor="black", linewidth=0.3, zorder=3)
        side = f" ({muscle.side})" if muscle.side else ""
        ax.set_title(f"{muscle.name}{side}\n{muscle.region}, peak {magnitude.max():.1f} mm", fontsize=8)
    fig.suptitle(f"livebridge basis: neutral and elements (deformed face; colour: displacement magnitude; "
                 f"arrows: motion x{arrow_gain:g})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


@click.command("show")
@click.argument("basis_spec", metavar="BASIS", type=BASIS_TYPE)
@click.option("--out", required=True, type=ImageFile(), help="Image file (.png).")
@force_option
@click.option("--markers", "markers_spec", type=InputPath(builtins=("design", *SHIPPED_MARKER_SETS)), default=None,
              help="Marker layout (.toml) to draw on the neutral face, a shipped one (builtin, builtin-68, ict-68), "
                   "or 'design' to design one now.")
@click.option("--yaw", type=FiniteFloat(-360, 360), default=15.0, show_default=True,
              help="View angle about the vertical axis, degrees.")
@click.option("--dpi", default=90, show_default=True, type=click.IntRange(30, 600))
@click.option("--muscle", "muscles", multiple=True, help="Only this element (repeatable; default: all).")
@click.option("--panel-size", default=3.0, show_default=True, type=FiniteFloat(1, 20), help="Inches per panel.")
@click.option("--crop-y", nargs=2, type=FiniteFloat(-1e4, 1e4), default=None, metavar="LOW HIGH",
              help="Frame only this range of heights of the neutral face (mm), e.g. -100 90.")
def show(basis_spec: str, out: Path, force: bool, markers_spec: str | None, yaw: float, dpi: int,
         muscles: tuple[str, ...], panel_size: float, crop_y: tuple[float, float] | None) -> None:
    """Render BASIS (a basis file or 'builtin'): the neutral face and each element, one panel each."""
    from livebridge.errors import InputError
    from livebridge.face.shipped import load_marker_set

    if crop_y is not None and not crop_y[0] < crop_y[1]:
        raise click.BadParameter(f"LOW {crop_y[0]:g} must be below HIGH {crop_y[1]:g}", param_hint="--crop-y")
    basis = load_basis(basis_spec)
    unknown = [name for name in muscles if name not in basis.names]
    if unknown:
        raise click.BadParameter(f"no element {unknown[0]!r} in the basis; it has {', '.join(basis.names)}",
                                 param_hint="--muscle")
    markers = None
    if markers_spec == "design":
        from livebridge.face.layout import design_markers

        markers = design_markers(basis)
    elif markers_spec is not None:
        try:
            markers = load_marker_set(markers_spec)
            markers.check_mesh(len(basis.triangles))
        except InputError as error:
            raise InputError(error.message, error.path or markers_spec, error.field) from None
    render_basis(basis, out, markers=markers, yaw_deg=yaw, dpi=dpi, muscles=muscles or None,
                 panel_inches=panel_size, crop_y=crop_y)
    click.echo(f"wrote {out}: neutral and {basis.n_muscles} elements of {basis_spec}")

"""Calibration report: per-camera RMS, coverage images, error histogram and advice."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livebridge.calibration.run import Calibration

GRID = (5, 4)  # coverage cells across x and y
RMS_ADVICE_PX = 0.5
COVERAGE_ADVICE = 0.75
MIN_VIEWS_ADVICE = 10
MIN_TILT_ADVICE_DEG = 20.0


def tilt_range_deg(calibration: Calibration, camera_index: int) -> float:
    """Largest angle between the board normals of two views this camera used, in degrees."""
    used = calibration.inliers[camera_index].any(axis=1) & np.isfinite(calibration.board2world[:, 0, 0])
    normals = calibration.board2world[used, :3, 2]
    if len(normals) < 2:
        return 0.0
    cos = np.clip(normals @ normals.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


def coverage(corners: np.ndarray, size: tuple[int, int], grid: tuple[int, int] = GRID) -> np.ndarray:
    """Detected corners per image cell, int (grid_y, grid_x); ``corners`` (n_views, n_corners, 2)."""
    points = corners.reshape(-1, 2)
    points = points[np.isfinite(points[:, 0])]
    width, height = size
    gx = np.clip((points[:, 0] / width * grid[0]).astype(int), 0, grid[0] - 1)
    gy = np.clip((points[:, 1] / height * grid[1]).astype(int), 0, grid[1] - 1)
    counts = np.zeros((grid[1], grid[0]), int)
    np.add.at(counts, (gy, gx), 1)
    return counts


def advice(calibration: Calibration) -> list[str]:
    """Plain-language advice for each camera whose RMS, coverage or view count is poor."""
    lines = []
    names = calibration.group.names
    rms = calibration.rms_px()
    views = calibration.views_used()
    corners = np.where(calibration.inliers[..., None], calibration.detections.corners, np.nan)
    for c, name in enumerate(names):
        size = calibration.group.cameras[c].size
        cells = coverage(corners[c], size)
        covered = (cells > 0).mean()
        if rms[c] > RMS_ADVICE_PX:
            lines.append(f"{name}: RMS {rms[c]:.2f} px is high; check focus and motion blur, that the board is flat "
                         "and the board spec (square size, corner counts) matches the print")
        if covered < COVERAGE_ADVICE:
            empty = [_cell_name(y, x) for y, x in zip(*np.nonzero(cells == 0))]
            lines.append(f"{name}: corners cover only {covered:.0%} of the image; move the board into the "
                         f"{', '.join(empty[:6])}{' ...' if len(empty) > 6 else ''} (lens distortion there is "
                         "extrapolated)")
        detected = np.isfinite(calibration.errors[c]).any(axis=1)
        dropped = detected & ~calibration.inliers[c].any(axis=1)
        if dropped.sum() > 0.2 * max(detected.sum(), 1):
            lines.append(f"{name}: {dropped.sum()} of {detected.sum()} board views disagree with the other cameras and "
                         "were dropped; check that the images are paired correctly across cameras (same instant)")
        tilt = tilt_range_deg(calibration, c)
        if tilt < MIN_TILT_ADVICE_DEG:
            lines.append(f"{name}: the board's orientation varies by only {tilt:.0f} degrees across views, so the "
                         "focal length is poorly determined; tilt the board up to about 45 degrees towards each side")
        if views[c] < MIN_VIEWS_ADVICE:
            lines.append(f"{name}: only {views[c]} views used; record at least {MIN_VIEWS_ADVICE}, tilting the board "
                         "up to about 45 degrees in different directions")
    return lines


def _cell_name(y: int, x: int) -> str:
    vertical = ["top", "upper", "middle", "lower", "bottom"][int(round(y / (GRID[1] - 1) * 4))]
    horizontal = ["left", "left-centre", "centre", "right-centre", "right"][int(round(x / (GRID[0] - 1) * 4))]
    return f"{vertical} {horizontal}"


def summary(calibration: Calibration) -> str:
    """A few lines for the terminal: per-camera RMS, views, outliers, world frame, advice."""
    meta = calibration.metadata()
    lines = [f"board {meta['board']}; world frame: {meta['world_frame']} (origin view {meta['origin_view']})"]
    for c, name in enumerate(calibration.group.names):
        camera = calibration.group.cameras[c]
        lines.append(f"  {name:12s} RMS {meta['rms_px'][name]:.3f} px ({meta['rms_all_px'][name]:.3f} px before "
                     f"pruning {meta['outliers'][name]} outliers), {meta['views_used'][name]} views, "
                     f"f = {camera.matrix[0, 0]:.1f}/{camera.matrix[1, 1]:.1f} px, "
                     f"centre = ({', '.join(f'{v:.1f}' for v in camera.center)}) mm")
    hints = advice(calibration)
    lines += ["advice:"] + ["  " + h for h in hints] if hints else ["no advice: coverage and RMS look good"]
    return "\n".join(lines)


def write_report(calibration: Calibration, folder: str | Path) -> list[Path]:
    """Write ``coverage_NAME.png`` per camera, ``reprojection_errors.png`` and ``report.txt`` into ``folder``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    detections = calibration.detections
    for c, name in enumerate(calibration.group.names):
        width, height = calibration.group.cameras[c].size
        corners = detections.corners[c]
        inliers = calibration.inliers[c]
        cells = coverage(np.where(inliers[..., None], corners, np.nan), (width, height))
        fig, ax = plt.subplots(figsize=(6.4, 6.4 * height / width + 0.6), dpi=100)
        ax.imshow(cells == 0, extent=(0, width, height, 0), cmap="Reds", vmin=0, vmax=2.5, alpha=0.6)
        seen = np.isfinite(corners[..., 0])
        ax.scatter(corners[seen & inliers][:, 0], corners[seen & inliers][:, 1], s=2, c="tab:blue", label="used")
        outliers = seen & ~inliers
        if outliers.any():
            ax.scatter(corners[outliers][:, 0], corners[outliers][:, 1], s=6, c="black", marker="x", label="outlier")
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: corner coverage (red cells: no corners)")
        ax.legend(loc="lower right", fontsize=7)
        path = folder / f"coverage_{_safe(name)}.png"
        fig.savefig(path, bbox_inches="tight")
        plt.close(fig)
        written.append(path)
    fig, ax = plt.subplots(figsize=(6.4, 4), dpi=100)
    finite = np.isfinite(calibration.errors)
    top = float(np.nanpercentile(calibration.errors, 99.5)) if finite.any() else 1.0
    bins = np.linspace(0, max(top, 1e-3), 50)
    for c, name in enumerate(calibration.group.names):
        values = calibration.errors[c][finite[c]]
        ax.hist(np.clip(values, 0, bins[-1]), bins=bins, histtype="step", label=f"{name}")
    ax.set_xlabel("reprojection error (px)")
    ax.set_ylabel("corners")
    ax.set_title("reprojection error after bundle adjustment")
    ax.legend(fontsize=7)
    path = folder / "reprojection_errors.png"
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)
    written.append(path)
    text = folder / "report.txt"
    text.write_text(summary(calibration) + "\n")
    written.append(text)
    return written


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)

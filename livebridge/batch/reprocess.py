"""One take, processed serially: the live path's reconstruction and solver on its raw frames, and/or the
offline solve of its labelled markers.

Every step is deterministic and runs on one BLAS thread (:func:`threadpoolctl.threadpool_limits`), so a take
gives the same bits wherever it runs: in this process or on any worker of a cluster.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.batch.jobs import ProcessSettings
from livebridge.errors import InputError

Progress = Callable[[int, int | None], None]
"""``progress(frames_done, frames_total or None)``."""


@dataclass(frozen=True, eq=False)
class ProcessedTake:
    """A take's results.

    Attributes
    ----------
    seq : ndarray of int, shape (n_frames,)
        Frame-set numbers (of the cameras).
    t : ndarray, shape (n_frames,)
        Capture time of each frame set, s (the recorded clock).
    contractions : ndarray, shape (n_frames, n_muscles)
    region_errors : ndarray, shape (n_frames, 2)
        RMS marker error of the upper and lower solve, mm.
    positions : ndarray, shape (n_frames, n_markers, 3)
        Labelled markers in the capture frame, mm, NaN unseen.
    displacements : ndarray, shape (n_frames, n_markers, 3)
        From neutral in the model frame, mm, NaN unseen.
    muscle_names, marker_names : tuple of str
    fps : float or None
    calibration : Path or None
        The calibration the take was (re)constructed with, copied with the results.
    """

    seq: np.ndarray
    t: np.ndarray
    contractions: np.ndarray
    region_errors: np.ndarray
    positions: np.ndarray
    displacements: np.ndarray
    muscle_names: tuple[str, ...]
    marker_names: tuple[str, ...]
    fps: float | None
    calibration: Path | None

    @property
    def n_frames(self) -> int:
        return len(self.t)


@functools.lru_cache(maxsize=4)
def load_face(basis_spec: str | Path, markers_spec: str | Path):
    """The basis and marker set (cached: a worker loads them once for all its takes)."""
    from livebridge.face.basis import Basis
    from livebridge.face.shipped import load_marker_set

    if basis_spec == "builtin":
        from livebridge.face.builtin import builtin_basis

        basis = builtin_basis()
    else:
        basis = Basis.load(basis_spec)
    markers = load_marker_set(markers_spec)
    markers.check_mesh(len(basis.triangles))
    return basis, markers


def process_take(take: Path, settings: ProcessSettings, progress: Progress | None = None) -> ProcessedTake:
    """Process one take directory by ``settings.stage`` (see :data:`livebridge.batch.jobs.STAGES`).

    Raises
    ------
    InputError
        The take is damaged or missing a file, the basis or marker set does not fit, ...: naming what.
    """
    from threadpoolctl import threadpool_limits

    basis, markers = load_face(settings.basis, settings.markers)
    with threadpool_limits(1):
        if settings.stage == "solve":
            return solve_recorded(take, basis, markers, settings.mode, progress)
        result = reconstruct(take, basis, markers, settings.calibration, settings.mode, progress)
        if settings.stage == "both":
            result = solve_markers(result, basis, markers, settings.mode, take)
        return result


# ------------------------------------------------------------------------------------------------ reconstruct
def _open_cameras(take: Path, calibration: Path | None):
    """Replay sources of the take's raw frames (unpaced) and their calibration, in one order."""
    from livebridge.calibration.calibfile import load_calibration
    from livebridge.calibration.cameras import CameraGroup
    from livebridge.take.directory import calibration_file, load_manifest, raw_frames_folder
    from livebridge.take.raw_frames import camera_names
    from livebridge.take.replay import ReplaySource

    manifest = load_manifest(take)
    raw_frames_folder(take)  # a clear error for a take recorded without frames
    calibration = calibration or calibration_file(take)
    if calibration is None:
        raise InputError("the take has no calibration recorded with it; give --calibration", take)
    by_name = {camera.name: camera for camera in load_calibration(calibration).cameras}
    sources = [ReplaySource(take, name, realtime=False) for name in camera_names(take)]
    missing = [s.source_id for s in sources if s.source_id not in by_name]
    if missing:
        raise InputError(f"no calibration for camera {missing[0]!r}; calibrated: {', '.join(by_name)}", calibration)
    return sources, CameraGroup([by_name[s.source_id] for s in sources]), calibration, manifest


def _frames_in_time_order(sources):
    """Every camera's frames merged by capture time (ties: camera order), as the synchroniser expects them."""
    heads = [source.read() for source in sources]
    while True:
        live = [k for k, frame in enumerate(heads) if frame is not None]
        if not live:
            return
        k = min(live, key=lambda i: (heads[i].t_capture, i))
        yield heads[k]
        heads[k] = sources[k].read()


def _framesets(sources, period_s: float, sync_tolerance: float):
    from livebridge.capture.sync import Synchronizer

    sync = Synchronizer([s.source_id for s in sources], period_s, tolerance_s=sync_tolerance * period_s)
    for frame in _frames_in_time_order(sources):
        yield from ((frameset, sync.dead) for frameset in sync.push(frame))
    yield from ((frameset, sync.dead) for frameset in sync.flush())


def _period(sources, manifest: dict) -> float:
    fps = manifest.get("fps") or min(s.capabilities.fps for s in sources)
    return 1.0 / float(fps)


def reconstruct(take: Path, basis, markers, calibration: Path | None = None, mode: str = "split-compensated",
                progress: Progress | None = None) -> ProcessedTake:
    """The take's raw frames through the live path: detection, :class:`~livebridge.reconstruct.pipeline.
    Reconstructor` and :class:`~livebridge.solve.solver.ContractionSolver`, frame set by frame set as
    :class:`~livebridge.runtime.pipeline.Pipeline` runs them (the first labelling waits for a frame set from
    every live camera; frame sets before it are not solved), without threads."""
    from livebridge.reconstruct.detect import detect_undistorted
    from livebridge.reconstruct.pipeline import ReconstructConfig, Reconstructor
    from livebridge.solve.solver import ContractionSolver, SolverConfig

    sources, cameras, calibration, manifest = _open_cameras(take, calibration)
    config, solver_config = ReconstructConfig(), SolverConfig(mode=mode)
    reconstructor = Reconstructor(cameras, markers, basis, config)
    total = max(manifest.get("frames_written", {}).values(), default=None)
    state, solver, solver_state, rows = reconstructor.initial_state(), None, None, []
    for source in sources:
        source.start()
    try:
        for done, (frameset, dead) in enumerate(_framesets(sources, _period(sources, manifest), 0.5), start=1):
            points_2d = [np.zeros((0, 2)) if frame is None else detect_undistorted(frame.image, camera, config.detect)
                         for frame, camera in zip(frameset.frames, cameras.cameras)]
            present = sum(frame is not None for frame in frameset.frames)
            if progress is not None:
                progress(done, total)
            if not state.labelled and present < len(sources) - len(dead):
                continue
            state, labelled = reconstructor.step(state, points_2d, frameset.t)
            if solver is None and state.alignment is not None:
                solver = ContractionSolver(basis, state.alignment.markers, solver_config)
                solver_state = solver.initial_state()
            if solver is None:
                continue
            solver_state, result = solver.step(solver_state, labelled.displacements)
            seq = next(f.seq for f in frameset.frames if f is not None)
            rows.append((seq, frameset.t, result.contractions, result.rms_error_mm, labelled.positions_world,
                         labelled.displacements))
    finally:
        for source in sources:
            source.stop()
    failed = [f"{s.source_id}: {s.error}" for s in sources if s.error]
    if failed:
        raise InputError(f"a camera could not be replayed ({'; '.join(failed)})", take)
    if not rows:
        raise InputError("no frame set could be labelled (the first must show the neutral face to every camera)",
                         take)
    return _stack(rows, basis.names, markers.names, manifest.get("fps"), calibration)


def _stack(rows, muscle_names, marker_names, fps, calibration) -> ProcessedTake:
    seq, t, contractions, errors, positions, displacements = zip(*rows)
    return ProcessedTake(np.array(seq, dtype=np.int64), np.array(t, dtype=np.float64), np.stack(contractions),
                         np.array(errors, dtype=np.float64).reshape(-1, 2), np.stack(positions),
                         np.stack(displacements), tuple(muscle_names), tuple(marker_names), fps, calibration)


# ------------------------------------------------------------------------------------------------ solve
def solve_recorded(take: Path, basis, markers, mode: str = "split-compensated",
                   progress: Progress | None = None) -> ProcessedTake:
    """The offline solve of a take directory's labelled markers (``markers.csv``), matched to ``markers`` by
    name."""
    from livebridge.take.directory import calibration_file, load_take_dir

    recorded = load_take_dir(take)
    if progress is not None:
        progress(0, recorded.n_frames)
    labelled = ProcessedTake(recorded.seq, recorded.t, recorded.contractions, recorded.region_errors,
                             recorded.markers, recorded.displacements, recorded.muscle_names, recorded.marker_names,
                             recorded.manifest.get("fps"), calibration_file(take))
    result = solve_markers(labelled, basis, markers, mode, take)
    if progress is not None:
        progress(recorded.n_frames, recorded.n_frames)
    return result


def solve_markers(take: ProcessedTake, basis, markers, mode: str, source: Path) -> ProcessedTake:
    """Contractions of ``take``'s labelled positions by the offline solve (:mod:`livebridge.solve.offline`, the
    neutral frame chosen against the marker set, as ``livebridge solve`` does)."""
    from livebridge.face.markers import match_markers
    from livebridge.solve.offline import neutral_for_set, solve_positions
    from livebridge.solve.solver import SolverConfig

    if not take.n_frames:
        raise InputError("the take has no frame to solve", source)
    positions = take.positions[:, match_markers(take.marker_names, markers, source=source)]
    choice = neutral_for_set(positions, basis, markers, None)
    solved = solve_positions(take.t, positions, basis, markers, choice, SolverConfig(mode=mode))
    return ProcessedTake(take.seq, solved.t, solved.solution.contractions, solved.solution.rms_error_mm,
                         positions, solved.displacements, tuple(basis.names), tuple(markers.names), take.fps,
                         take.calibration)

"""The jobs of a batch: one per take, planned and checked before any work starts."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from livebridge.errors import InputError

STAGES = ("reconstruct", "solve", "both")
"""``reconstruct``: raw frames -> labelled markers and contractions, as the live pipeline makes them;
``solve``: a take's labelled markers -> contractions by the offline solve; ``both``: one, then the other."""


@dataclass(frozen=True)
class ProcessSettings:
    """What every take of a batch is processed with.

    Attributes
    ----------
    stage : str
        One of :data:`STAGES`.
    basis : str or Path
        ``builtin`` or a basis ``.npz``.
    markers : str or Path
        A shipped marker-set name or a marker-set ``.toml``.
    calibration : Path or None
        For ``reconstruct``: the rig's calibration; None: each take's own (recorded with it).
    mode : str
        Solver region mode (:class:`~livebridge.solve.solver.SolverConfig`).
    """

    stage: str = "solve"
    basis: str | Path = "builtin"
    markers: str | Path = "builtin"
    calibration: Path | None = None
    mode: str = "split-compensated"

    def __post_init__(self):
        if self.stage not in STAGES:
            raise InputError(f"expected one of {', '.join(STAGES)}, got {self.stage!r}", field="--stage")


@dataclass(frozen=True)
class TakeJob:
    """One take to process.

    Attributes
    ----------
    take : Path
        The recorded take directory.
    out : Path
        The batch's output folder; the take's results go to ``out/NAME/`` and ``out/NAME.npz``.
    settings : ProcessSettings
    force : bool
        Replace results that exist.
    """

    take: Path
    out: Path
    settings: ProcessSettings
    force: bool = False

    @property
    def name(self) -> str:
        return self.take.name

    @property
    def take_out(self) -> Path:
        """The output take directory."""
        return self.out / self.name

    @property
    def npz_out(self) -> Path:
        """The output take at full precision (:class:`livebridge.take.npz.Take`)."""
        return self.out / f"{self.name}.npz"


@dataclass(frozen=True)
class TakeOutcome:
    """How one take went.

    Attributes
    ----------
    name : str
        The take's folder name.
    ok : bool
    frames : int
        Frame sets written (0 on failure).
    seconds : float
        Wall time of the take's work.
    reason : str
        Why it failed (empty when ``ok``).
    """

    name: str
    ok: bool
    frames: int = 0
    seconds: float = math.nan
    reason: str = ""


def plan_jobs(takes, out: Path, settings: ProcessSettings, force: bool = False) -> list[TakeJob]:
    """One job per take, in the order given.

    Refused up front (raises :class:`InputError`): no take, the output folder missing, two takes of the same
    name (their results would collide), a take given twice, and results already in ``out`` without ``force``.
    Whether each take can be processed is found out by its own job, so one bad take does not stop the others.
    """
    takes = [Path(t) for t in takes]
    if not takes:
        raise InputError("no take given", field="TAKE_DIR")
    out = Path(out)
    if not out.is_dir():
        raise InputError("the output folder does not exist; create it first", out, "--out")
    seen: dict[str, Path] = {}
    for take in takes:
        other = seen.setdefault(take.name, take)
        if other is not take:
            what = "is given twice" if other.resolve() == take.resolve() else f"has the same name as {other}"
            raise InputError(f"{what}: results are named after the take's folder", take, "TAKE_DIR")
    jobs = [TakeJob(take, out, settings, force) for take in takes]
    if not force:
        for job in jobs:
            for path in (job.take_out, job.npz_out):
                if path.exists():
                    raise InputError("already exists; add --force to overwrite it", path, "--out")
    return jobs

"""Session files fuzzed from the valid schema: every document either loads, or is refused with one error
naming the file (an :class:`~livebridge.errors.InputError`, one ``Error:`` line from ``livebridge run``),
never another exception and never a hang.

Documents are built from the tables and keys :mod:`livebridge.runtime.session` knows, each value valid or
mutated (another type, NaN, infinity, negative, huge), with unknown keys and tables added and known ones
left out.
"""

from __future__ import annotations

import math

import pytest
import tomli_w
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from livebridge.cli import main
from livebridge.errors import InputError
from livebridge.runtime.session import load_session

_PATHS = st.sampled_from(["builtin", "nowhere.toml", "face.npz", ".", "../x", ""])
_PORTS = st.integers(0, 70000)
_FLOATS = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([0.0, -1.0, 0.25, 1e308])
_SCHEMA = {  # table -> key -> strategy of a valid-looking value
    "": {"calibration": _PATHS},
    "cameras": {"urls": st.lists(st.sampled_from(["sim://rig?cameras=2&realtime=0", "replay://take", "v4l2:///x",
                                                  "webcam0", "sim://rig?cameras=1000"]), max_size=3),
                "sync_tolerance": _FLOATS},
    "face": {"basis": _PATHS, "markers": _PATHS},
    "reconstruct": {"tolerance_px": _FLOATS, "max_residual_px": _FLOATS},
    "solver": {"mode": st.sampled_from(["split-compensated", "split", "joint", "fast"]), "exaggerate": st.booleans(),
               "sweeps": st.integers(-5, 10)},
    "servo": {"rig": _PATHS},
    "outputs.render": {"enabled": st.booleans(), "host": st.sampled_from(["127.0.0.1", "0.0.0.0", "::1", ""]),
                       "port": _PORTS, "allowed_origins": st.lists(st.sampled_from(["http://a:1", "evil", ""]),
                                                                   max_size=2)},
    "outputs.vmc": {"enabled": st.booleans(), "host": st.sampled_from(["127.0.0.1", "255.255.255.255", "x"]),
                    "port": _PORTS, "case": st.sampled_from(["camel", "pascal", "SHOUT"]),
                    "mapping": st.sampled_from(["identity", "arkit"]) | st.just({"jaw": {"jawOpen": 1.0}})},
    "recording": {"enabled": st.booleans(), "directory": _PATHS, "raw_frames": st.booleans(),
                  "frame_format": st.sampled_from(["pgm", "png", "jpg"])},
    "runtime": {"status_interval": _FLOATS, "frames": st.integers(-3, 10)},
}
_SCALARS = (st.integers(-2**63, 2**63 - 1) | _FLOATS | st.text(max_size=8) | st.booleans()
            | st.sampled_from([2**63 - 1, -2**63, 10**18]))
_ANY = st.recursive(_SCALARS, lambda inner: st.lists(inner, max_size=3)
                    | st.dictionaries(st.text("abcxyz_", min_size=1, max_size=5), inner, max_size=3), max_leaves=6)
_NAMES = st.sampled_from(["calibraton", "urls", "port", "mode", "render", "camera", "x"])


@st.composite
def session_documents(draw) -> dict:
    """A session document: some tables and keys of the schema, each value valid or mutated, plus strays."""
    document: dict = {}
    for table, keys in _SCHEMA.items():
        if table and not draw(st.booleans()):
            continue  # a table left out
        target = document
        for part in filter(None, table.split(".")):
            target = target.setdefault(part, {})
        for key, valid in keys.items():
            if draw(st.integers(0, 3)) == 0:
                continue  # a key left out
            target[key] = draw(valid if draw(st.integers(0, 3)) else _ANY)
        if draw(st.integers(0, 5)) == 0:
            target[draw(_NAMES)] = draw(_ANY)  # an unknown key (or a known one with any value)
    if draw(st.integers(0, 5)) == 0:
        document[draw(_NAMES)] = draw(_ANY)
    return document


def _toml(document: dict) -> str:
    """TOML text of ``document``; NaN and infinity as TOML's ``nan`` / ``inf``."""
    return tomli_w.dumps(document)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                  HealthCheck.too_slow])
@given(document=session_documents())
def test_a_fuzzed_session_loads_or_is_one_error_naming_the_file(tmp_path, document):
    path = tmp_path / "session.toml"
    path.write_text(_toml(document))
    try:
        session = load_session(path)
    except InputError as error:
        assert str(path) in str(error), str(error)
    else:
        assert math.isfinite(session.status_interval) and session.status_interval > 0
        assert math.isfinite(session.reconstruct.tolerance_px) and session.reconstruct.tolerance_px > 0
        assert 0 < session.sync_tolerance <= 0.5 and session.frames >= 0 and 1 <= session.solver.sweeps <= 100
        assert 0 <= session.render.port <= 65535 and 1 <= session.vmc.port <= 65535
        return
    result = CliRunner().invoke(main, ["run", str(path)])
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.output
    assert len(errors) == 1 and str(path) in errors[0] and "internal error" not in errors[0], result.output


@pytest.mark.parametrize("extra", ["[solver]\nsweeps = 9223372036854775807\n", "[outputs.vmc]\nport = 0\n",
                                   "[reconstruct]\ntolerance_px = inf\n", "[runtime]\nstatus_interval = 1e999\n"])
def test_values_that_would_hang_or_crash_later_are_refused_by_the_loader(tmp_path, extra):
    path = tmp_path / "session.toml"
    path.write_text('[cameras]\nurls = ["sim://rig"]\n' + extra)
    with pytest.raises(InputError, match="session.toml"):
        load_session(path)

"""Rig files: every malformed one is refused naming file, table and key; `servo limits` keeps the user's file."""

from __future__ import annotations

import copy
import math
import os

import pytest
import tomli_w
from click.testing import CliRunner
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from livebridge.cli import main
from livebridge.errors import InputError
from livebridge.servo.rig import backup_path, load_rig

RIG = """\
# Test head: one jaw servo, one smile servo.
frame_rate = 50.0                   # targets per second

[safety]
watchdog_s = 0.5                    # ease to neutral after this
soft_start_s = 1.5
ease_s = 2.0
estop = "stop"

[buses.head]
url = "simdynamixel://?ids=1-2&delay=0"

[servos.jaw]
bus = "head"
id = 1
muscles = { jaw = 1.0 }
curve = "gamma"
gamma = 0.8
neutral = 2048                      # raw ticks
min = 1800                          # reached at drive -1
max = 2600                          # reached at drive +1
slew = 3000
filter = { kind = "exponential", tau = 0.03 }

[servos.smile]
bus = "head"
id = 2
muscles = { zygomatic_major_L = 1.0 }
curve = { kind = "piecewise", points = [[0, 0], [1, 1]] }
neutral = 2048
min = 2200
max = 1700
"""


def _lines_of_error(result) -> list[str]:
    return [line for line in result.output.splitlines() if line.startswith("Error:")]


def test_the_reference_rig_loads(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(RIG)
    rig = load_rig(path)
    assert [s.name for s in rig.servos] == ["jaw", "smile"] and rig.servo("jaw").slew == 3000


# (old text, new text, what the error line must name besides the file)
MALFORMED = [
    ("slew = 3000", "slwe = 50", "servos.jaw.slwe"),
    ("ease_s = 2.0", "ease_s = 2.0\nwatchdg_s = 0.5", "safety.watchdg_s"),
    ("[safety]", "[safty]", "safty"),
    ("soft_start_s = 1.5", "soft_start_s = -5", "safety.soft_start_s"),
    ("soft_start_s = 1.5", "soft_start_s = nan", "safety.soft_start_s"),
    ("watchdog_s = 0.5", "watchdog_s = 0", "safety.watchdog_s"),
    ("watchdog_s = 0.5", "watchdog_s = 1e300", "safety.watchdog_s"),
    ("ease_s = 2.0", "ease_s = -inf", "safety.ease_s"),
    ('estop = "stop"', 'estop = "halt"', "safety.estop"),
    ('estop = "stop"', "estop = 1", "safety.estop"),
    ("frame_rate = 50.0", "frame_rate = 0", "frame_rate"),
    ("frame_rate = 50.0", "frame_rate = 1e9", "frame_rate"),
    ("frame_rate = 50.0", 'frame_rate = "fast"', "frame_rate"),
    ("frame_rate = 50.0", "frame_rate = 50.0\nframe_rat = 50.0", "frame_rat"),
    ("min = 1800 ", "min = nan ", "servos.jaw.min"),
    ("max = 2600 ", "max = inf ", "servos.jaw.max"),
    ("max = 2600 ", "max = 5000 ", "servos.jaw"),
    ("min = 1800 ", "min = -1 ", "servos.jaw"),
    ("neutral = 2048 ", 'neutral = "2048" ', "servos.jaw.neutral"),
    ("neutral = 2048 ", "neutral = true ", "servos.jaw.neutral"),
    ("neutral = 2048 ", "neutral = 100 ", "servos.jaw.neutral"),
    ("id = 1", "id = true", "servos.jaw.id"),
    ("id = 1", "id = 1.5", "servos.jaw.id"),
    ("id = 1", "id = 300", "servos.jaw.id"),
    ("id = 1", "channel = 1", "servos.jaw.channel"),
    ("id = 2", "id = 1", "servos.smile.id"),
    ("slew = 3000", "slew = 0", "servos.jaw.slew"),
    ("slew = 3000", "slew = [3000]", "servos.jaw.slew"),
    ('curve = "gamma"', 'curve = "linear"', "servos.jaw.gamma"),  # gamma left behind would be ignored
    ("gamma = 0.8", "gamma = -1", "servos.jaw.gamma"),
    ("gamma = 0.8", "gamma = nan", "servos.jaw.gamma"),
    ('curve = "gamma"', 'curve = "cubic"', "servos.jaw.curve"),
    ("points = [[0, 0], [1, 1]]", 'points = [[0, "a"], [1, 1]]', "servos.smile.curve.points"),
    ("points = [[0, 0], [1, 1]]", "points = [[0, 0, 0], [1, 1]]", "servos.smile.curve.points"),
    ("points = [[0, 0], [1, 1]]", "points = [[1, 0], [0, 1]]", "servos.smile.curve"),
    ("points = [[0, 0], [1, 1]] }", "points = [[0, 0], [1, 1]], gama = 2 }", "servos.smile.curve.gama"),
    ("tau = 0.03", "beta = 0.03", "servos.jaw.filter.beta"),
    ("tau = 0.03", "tau = -0.03", "servos.jaw.filter.tau"),
    ('kind = "exponential"', "kind = 5", "servos.jaw.filter.kind"),
    ('kind = "exponential"', 'kind = "kalman"', "servos.jaw.filter.kind"),
    ("muscles = { jaw = 1.0 }", "muscles = { jaw = nan }", "servos.jaw.muscles.jaw"),
    ("muscles = { jaw = 1.0 }", "muscles = { jaw = '1' }", "servos.jaw.muscles.jaw"),
    ("muscles = { jaw = 1.0 }", "muscles = { jw = 1.0 }", "servos.jaw.muscles.jw"),
    ("muscles = { jaw = 1.0 }", "muscles = {}", "servos.jaw.muscles"),
    ("muscles = { jaw = 1.0 }", "muscles = 1.0", "servos.jaw.muscles"),
    ('bus = "head"\nid = 1', 'bus = "neck"\nid = 1', "servos.jaw.bus"),
    ('url = "simdynamixel://?ids=1-2&delay=0"', "url = 5", "buses.head.url"),
    ('url = "simdynamixel://?ids=1-2&delay=0"', 'url = "bogus:///dev/x"', "buses.head.url"),
    ('url = "simdynamixel://?ids=1-2&delay=0"', 'url = "simdynamixel://?ids=1-2"\nbaud = 9600', "buses.head.baud"),
    ("slew = 3000", "slew = 3000\n[servos.jaw.limits]\nmin = 1", "servos.jaw.limits"),
    ("[servos.smile]", "[servos.smile]\nmodel = 12", "servos.smile.model"),
    ("[servos.smile]", "[servos.smile]\nsmile = 1", "servos.smile.smile"),
    ("[buses.head]", "servos = 5\n[buses.head]", "servos"),
    ("min = 1800 ", "min = = 1800 ", "not valid TOML"),
]


@pytest.mark.parametrize("old, new, named", MALFORMED, ids=[case[1].replace("\n", " ") for case in MALFORMED])
def test_malformed_rig_is_one_error_line_and_stays_unchanged(tmp_path, old, new, named):
    assert old in RIG
    path = tmp_path / "rig.toml"
    path.write_text(RIG.replace(old, new, 1))
    before = path.read_bytes()
    result = CliRunner().invoke(main, ["servo", "limits", str(path), "jaw", "--max", "2500"])
    assert result.exit_code != 0, result.output
    assert isinstance(result.exception, SystemExit) and "Traceback" not in result.output
    errors = _lines_of_error(result)
    assert len(errors) == 1, result.output
    assert str(path) in errors[0] and named in errors[0], errors[0]
    assert path.read_bytes() == before and not backup_path(path).exists()


WHOLE_FILES = [
    (b"", "buses"),
    (b"\xff\xfe[buses]", "not UTF-8"),
    (b"\x00\x01\x02", "not valid TOML"),
    (RIG.encode().replace(b"[servos.jaw]", b"[[servos.jaw]]"), "servos.jaw: expected a table, got an array"),
    (b"[[servos]]\nbus = 1\n[buses.head]\nurl = 'simssc32://'\n", "servos"),
    (b"buses = 'head'\nservos = {}\n", "buses"),
]


@pytest.mark.parametrize("content, named", WHOLE_FILES)
def test_malformed_rig_files(tmp_path, content, named):
    path = tmp_path / "rig.toml"
    path.write_bytes(content)
    result = CliRunner().invoke(main, ["servo", "limits", str(path), "jaw", "--max", "2500"])
    assert result.exit_code != 0 and isinstance(result.exception, SystemExit), result.output
    errors = _lines_of_error(result)
    assert len(errors) == 1 and str(path) in errors[0] and named in errors[0], result.output
    assert path.read_bytes() == content and not backup_path(path).exists()


def test_limits_keeps_comments_and_layout_and_a_backup(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(RIG)
    result = CliRunner().invoke(main, ["servo", "limits", str(path), "jaw", "--min", "1850", "--neutral", "2000.5"])
    assert result.exit_code == 0, result.output
    assert path.read_text() == RIG.replace("min = 1800 ", "min = 1850 ").replace(
        "neutral = 2048                      # raw ticks", "neutral = 2000.5                      # raw ticks")
    assert backup_path(path).read_bytes() == RIG.encode() and str(backup_path(path)) in result.output
    jaw = load_rig(path).servo("jaw")
    assert (jaw.minimum, jaw.neutral, jaw.maximum) == (1850, 2000.5, 2600)
    assert not [p for p in os.listdir(tmp_path) if p.endswith((".tmp", ".partial"))]  # the atomic write left nothing


def test_limits_edits_other_layouts(tmp_path):
    """Inline and dotted tables are edited where they are; the next run's backup is the previous file."""
    text = ('[buses.head]\nurl = "simmaestro://?channels=4"  # hobby servos\n\n'
            '[servos]\nbrow = { bus = "head", channel = 0, muscles = { frontalis_L = 1.0 }, neutral = 1500, '
            'min = 1200, max = 1800 }  # inline\n'
            'lip.bus = "head"\nlip.channel = 1\nlip.muscles = { orbicularis_oris = 1.0 }\n'
            'lip.neutral = 1500\nlip.min = 1300\nlip.max = 1700   # dotted\n')
    path = tmp_path / "head.toml"
    path.write_text(text)
    for servo, option, value in (("brow", "--max", "1750"), ("lip", "--min", "1350.25")):
        previous = path.read_bytes()
        result = CliRunner().invoke(main, ["servo", "limits", str(path), servo, option, value])
        assert result.exit_code == 0, result.output
        assert backup_path(path).read_bytes() == previous
    assert path.read_text() == text.replace("max = 1800 }", "max = 1750 }").replace("lip.min = 1300",
                                                                                    "lip.min = 1350.25")


def test_limits_follows_a_symlink_and_keeps_the_mode(tmp_path):
    real = tmp_path / "real.toml"
    real.write_text(RIG)
    real.chmod(0o640)
    link = tmp_path / "rig.toml"
    link.symlink_to(real)
    result = CliRunner().invoke(main, ["servo", "limits", str(link), "jaw", "--max", "2500"])
    assert result.exit_code == 0, result.output
    assert link.is_symlink() and load_rig(real).servo("jaw").maximum == 2500
    assert real.stat().st_mode & 0o777 == 0o640


# -- fuzzing rig documents: valid schema, then mutations ------------------------------------------------------

VALID = {
    "frame_rate": 50.0,
    "safety": {"watchdog_s": 0.5, "soft_start_s": 1.5, "ease_s": 2.0, "estop": "stop"},
    "buses": {"head": {"url": "simdynamixel://?ids=1-3"}, "hobby": {"url": "simmaestro://?channels=6"}},
    "servos": {
        "jaw": {"bus": "head", "id": 1, "muscles": {"jaw": 1.0, "orbicularis_oris": -0.3}, "curve": "gamma",
                "gamma": 0.8, "neutral": 2048, "min": 1800, "max": 2600, "slew": 3000,
                "filter": {"kind": "one_euro", "min_cutoff": 2.0, "beta": 0.5}},
        "smile": {"bus": "hobby", "channel": 2, "muscles": {"zygomatic_major_L": 1.0},
                  "curve": {"kind": "piecewise", "points": [[0, 0], [0.5, 0.8], [1, 1]]},
                  "neutral": 1500, "min": 1200, "max": 1900, "filter": {"kind": "exponential", "tau": 0.02}},
    },
}

_SCALARS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**20, 10**20), st.booleans(),
    st.sampled_from(["", "head", "hobby", "jaw", "gamma", "linear", "piecewise", "one_euro", "none", "stop",
                     "home", "simdynamixel://?ids=1", "simssc32://", "bogus://", "dynamixel:///dev/null"]),
    st.sampled_from([0, -1, -5, 1e308, -1e308, 4095, 4096, 64, 4080, 252, 253, 23, 24]),
)
_VALUES = st.recursive(_SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                         st.dictionaries(st.text(max_size=6), inner, max_size=3)),
                       max_leaves=6)
_KEYS = st.one_of(st.sampled_from(["slwe", "watchdg_s", "safty", "id", "channel", "min", "max", "neutral", "kind",
                                   "tau", "gamma", "points", "url", "bus", "muscles", "jaw", "filter", "curve"]),
                  st.text(min_size=1, max_size=8))


def _tables(document: dict, path=()) -> list[tuple]:
    """Paths of every table in the document (the top level is ``()``)."""
    out = [path]
    for key, value in document.items():
        if isinstance(value, dict):
            out += _tables(value, (*path, key))
    return out


def _at(document: dict, path: tuple) -> dict:
    for key in path:
        document = document[key]
    return document


@st.composite
def rig_documents(draw) -> dict:
    document = copy.deepcopy(VALID)
    for _ in range(draw(st.integers(0, 3))):
        table = _at(document, draw(st.sampled_from(_tables(document))))
        action = draw(st.sampled_from(["set", "replace", "nudge", "nudge", "delete", "rename"]))
        if action == "set" or not table:
            table[draw(_KEYS)] = draw(_VALUES)
            continue
        key = draw(st.sampled_from(sorted(table)))
        if action == "replace":
            table[key] = draw(_VALUES)
        elif action == "nudge":  # a plausible number: often still a valid rig, sometimes just outside
            table[key] = draw(st.one_of(st.integers(-2, 4100), st.floats(-1.0, 4100.0)))
        elif action == "delete":
            del table[key]
        else:
            table[key + draw(st.sampled_from(["_", "s", "x"]))] = table.pop(key)
    return document


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(document=rig_documents())
def test_fuzzed_rig_loads_inside_the_range_or_is_refused_naming_the_file(tmp_path, document):
    path = tmp_path / "rig.toml"
    path.write_text(tomli_w.dumps(document))
    try:
        rig = load_rig(path)
    except InputError as error:
        assert str(path) in str(error)
        event("refused")
        return
    event("loaded")
    for servo in rig.servos:
        low, high = rig.buses[servo.bus].facts.raw_range
        for value in (servo.minimum, servo.neutral, servo.maximum, servo.slew):
            assert math.isfinite(value)
        assert low <= servo.low <= servo.neutral <= servo.high <= high and servo.slew > 0
    for value in (rig.frame_rate, rig.watchdog_s, rig.soft_start_s, rig.ease_s):
        assert math.isfinite(value) and value >= 0


@pytest.mark.parametrize("url", ["simdynamixel://?ids=1-16", "simmaestro://?channels=16", "simssc32://"])
def test_a_saved_rig_passes_the_strict_loader(tmp_path, url):
    from livebridge.servo.rig import demo_rig

    rig = demo_rig(url)
    rig.save(tmp_path / "rig.toml")
    assert load_rig(tmp_path / "rig.toml").servos == rig.servos

"""The device registry and its strict URLs: one parser for camera and servo URLs, schemes declared by their
owners, simulators registered like real drivers."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from livebridge.devices.registry import bus_facts, bus_schemes, camera_schemes, open_bus, open_camera, open_cameras
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError
from livebridge.servo.bus import ServoBus
from livebridge.servo.rig import rig_from_dict

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("url, parameter", [
    ("simdynamixel://?ids=1-4&bauds=1", "bauds"),
    ("simmaestro://?channels=8&chanels=8", "chanels"),
    ("simssc32://?sead=1", "sead"),
    ("dynamixel:///dev/does-not-exist?buad=1000000", "buad"),  # named before the port is opened
    ("maestro:///dev/does-not-exist?devcie=12", "devcie"),
    ("ssc32:///dev/does-not-exist?baud=115200&process=1", "process"),  # a simulator's parameter
])
def test_unknown_servo_url_parameter_is_named(url, parameter):
    with pytest.raises(InputError, match=f"unknown parameter.*{parameter}") as error:
        open_bus(url)
    assert error.value.field == parameter and error.value.path == url


@pytest.mark.parametrize("url, parameter", [
    ("simdynamixel://?ids=1-4&ids=5", "ids"),
    ("simmaestro://?device=12&device=13", "device"),
    ("dynamixel:///dev/ttyUSB0?baud=1000000&baud=57600", "baud"),
    ("sim://rig?cameras=2&cameras=3", "cameras"),
    ("v4l2:///dev/video0?width=640&width=1280", "width"),
])
def test_repeated_url_parameter_is_named(url, parameter):
    with pytest.raises(InputError, match=f"parameter '{parameter}' given 2 times") as error:
        if url.startswith(("sim:", "v4l2:")):
            open_cameras(url)
        else:
            open_bus(url)
    assert error.value.field == parameter and error.value.path == url


@pytest.mark.parametrize("url, parameter", [
    ("sim://rig?cameras=2&nosie=1", "nosie"),
    ("v4l2:///dev/video0?widht=640", "widht"),
    ("replay:///tmp/take?realtim=0", "realtim"),
])
def test_unknown_camera_url_parameter_is_named(url, parameter):
    with pytest.raises(InputError, match=f"unknown parameter.*{parameter}") as error:
        open_cameras(url)
    assert error.value.field == parameter and error.value.path == url


def test_typed_parameters():
    url = DeviceURL.parse("simdynamixel://?process=yes&corrupt=0.5&seed=3&flag=OFF")
    assert url.take("process", bool) is True and url.take("flag", bool) is False
    assert url.take("corrupt", float) == 0.5 and url.take("seed", int) == 3 and url.take("drop", float, 0.0) == 0.0
    with pytest.raises(InputError, match="parameter 'seed': expected float") as error:
        DeviceURL.parse("x://?seed=abc").take("seed", float)
    assert error.value.field == "seed"
    with pytest.raises(InputError, match="process"):
        open_bus("simdynamixel://?ids=1&process=maybe")
    with pytest.raises(InputError, match="scheme"):
        DeviceURL.parse("/dev/ttyUSB0")


def test_unknown_schemes_list_the_known_ones():
    with pytest.raises(InputError, match="unknown bus URL scheme 'canbus'.*simdynamixel"):
        open_bus("canbus:///dev/x")
    with pytest.raises(InputError, match="unknown camera URL scheme 'rtsp'.*replay.*sim.*v4l2"):
        open_camera("rtsp://host/stream")
    with pytest.raises(InputError, match="unknown bus URL scheme 'v4l2'"):
        bus_facts("v4l2:///dev/video0")


def test_schemes_are_declared_by_their_owners():
    assert set(camera_schemes()) == {"v4l2", "depthai", "replay", "sim", "node"}
    buses = bus_schemes()
    assert set(buses) == {"dynamixel", "maestro", "ssc32", "simdynamixel", "simmaestro", "simssc32"}
    for scheme, (opener, facts) in buses.items():
        owner = "livebridge.simulators." if scheme.startswith("sim") else "livebridge.drivers."
        assert opener.startswith(owner) and facts.startswith("livebridge.drivers.")


def test_a_simulated_bus_has_its_real_drivers_facts():
    for real, simulated in (("dynamixel:///dev/ttyUSB0", "simdynamixel://?ids=1-4"),
                            ("maestro:///dev/ttyACM0", "simmaestro://"), ("ssc32:///dev/ttyUSB1", "simssc32://")):
        assert bus_facts(real) == bus_facts(simulated)
        facts = bus_facts(real)
        assert facts.raw_range[0] <= facts.centre <= facts.raw_range[1]
    assert bus_facts("dynamixel:///dev/ttyUSB0").raw_range == (0, 4095)
    assert bus_facts("maestro:///dev/ttyACM0").address_range == (0, 23)


def test_rig_file_bus_url_is_parsed_strictly():
    rig = {"buses": {"head": {"url": "simdynamixel://?ids=1&ids=2"}},
           "servos": {"jaw": {"bus": "head", "id": 1, "muscles": {"jaw": 1.0}, "neutral": 2048, "min": 1800,
                              "max": 2300}}}
    with pytest.raises(InputError, match="given 2 times") as error:
        rig_from_dict(rig, "rig.toml")
    assert error.value.field == "buses.head.url"


@pytest.mark.parametrize("url", ["simmaestro://?channels=4", "simssc32://?channels=4"])
def test_hobby_servo_buses_implement_the_whole_protocol(url):
    bus = open_bus(url, timeout=2.0)
    try:
        assert isinstance(bus, ServoBus)
        assert bus.status == {} and bus.faults == {}
        assert bus.recover(0) is False  # no reboot for a hobby servo
    finally:
        bus.close()
    assert bus.companion is None  # the simulator closed with the bus


def _imports(path: Path) -> set[str]:
    """Every module a file imports, also inside functions (``from a import b`` counts as ``a`` and ``a.b``)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _file(module: str) -> Path:
    parts = module.split(".")[1:]
    if parts[0] in ("drivers", "simulators"):
        return ROOT.joinpath(*parts).with_suffix(".py")
    return ROOT.joinpath("livebridge", *parts).with_suffix(".py")


def test_implementations_never_import_the_registry_and_drivers_never_import_simulators():
    targets = list(camera_schemes().values()) + [t for entry in bus_schemes().values() for t in entry]
    files = {_file(target.split(":")[0]) for target in targets}
    files |= {_file(m) for m in ("livebridge.devices.url", "livebridge.capture.sources", "livebridge.servo.bus")}
    files |= set((ROOT / "drivers").glob("*.py")) | set((ROOT / "simulators").glob("*.py"))
    assert _file("livebridge.take.replay") in files and _file("livebridge.simulators.rig") in files
    for path in files:
        imported = _imports(path)
        assert "livebridge.devices.registry" not in imported, path
        if path.parent.name == "drivers":
            assert not any(name.startswith("livebridge.simulators") for name in imported), path

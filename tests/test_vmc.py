"""VMC/OSC output: real datagrams on a local UDP socket, decoded by python-osc."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage

from livebridge.errors import InputError
from livebridge.face.basis import CHOE_KO_MUSCLES
from livebridge.output.vmc import (
    APPLY_ADDRESS,
    ARKIT_MAPPING,
    DEFAULT_PORT,
    VAL_ADDRESS,
    BlendshapeMap,
    VMCEncoder,
    VMCOutput,
    convert_case,
)

NAMES = tuple(m.name for m in CHOE_KO_MUSCLES)


@pytest.fixture
def receiver():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2)
    yield sock
    sock.close()


def _receive_frame(sock) -> tuple[list[tuple[str, float]], list[int], bool]:
    """Datagrams up to and including the one that carries Apply: (name, value) pairs, sizes, apply seen."""
    values, sizes = [], []
    while True:
        datagram = sock.recv(65536)
        sizes.append(len(datagram))
        assert OscBundle.dgram_is_bundle(datagram)
        applied = False
        for content in OscBundle(datagram):
            assert isinstance(content, OscMessage)
            assert not applied, "Apply must be the last message"
            if content.address == APPLY_ADDRESS:
                assert content.params == []
                applied = True
            else:
                assert content.address == VAL_ADDRESS
                name, value = content.params
                values.append((name, value))
        if applied:
            return values, sizes, True


def test_default_map_sends_arkit_names_and_values(receiver):
    x = np.linspace(0, 1, 16)
    port = receiver.getsockname()[1]
    with VMCOutput(NAMES, port=port) as out:
        assert out.send_contractions(x) >= 1
        values, sizes, applied = _receive_frame(receiver)
    got = dict(values)
    assert applied and len(got) == len(values)  # each name once
    expected = {}
    for muscle, targets in ARKIT_MAPPING.items():
        for shape, weight in targets.items():
            expected[shape] = expected.get(shape, 0) + weight * x[NAMES.index(muscle)]
    assert set(got) == set(expected)
    for shape, value in expected.items():
        assert got[shape] == pytest.approx(min(max(value, 0), 1), abs=1e-6)
    assert "jawOpen" in got and got["jawOpen"] == pytest.approx(1.0)
    assert all(size <= 1472 for size in sizes)


@pytest.mark.parametrize("case,name", [("camel", "mouthSmileLeft"), ("pascal", "MouthSmileLeft"),
                                       ("lower", "mouthsmileleft"), ("snake", "mouth_smile_left")])
def test_case_is_configurable(receiver, case, name):
    x = np.zeros(16)
    x[NAMES.index("zygomatic_major_L")] = 0.75
    with VMCOutput(NAMES, port=receiver.getsockname()[1], case=case) as out:
        out.send_contractions(x)
        got = dict(_receive_frame(receiver)[0])
    assert got[name] == pytest.approx(0.75)
    assert convert_case("mouthSmileLeft", case) == name


def test_many_blendshapes_split_into_bundles_under_the_limit(receiver):
    """200 long names cannot fit one datagram: several bundles, each small enough, Apply only at the end."""
    muscles = [f"muscle_with_a_long_name_{k:03d}" for k in range(200)]
    x = np.random.default_rng(3).uniform(0, 1, 200)
    with VMCOutput(muscles, port=receiver.getsockname()[1], mapping="identity", max_datagram=1200) as out:
        n = out.send_contractions(x)
        values, sizes, _ = _receive_frame(receiver)
    assert n == len(sizes) > 5 and max(sizes) <= 1200
    assert [name for name, _ in values] == muscles
    assert np.allclose([v for _, v in values], x, atol=1e-6)


def test_encoder_matches_python_osc_builder():
    from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
    from pythonosc.osc_message_builder import OscMessageBuilder

    names = ("jawOpen", "eyeBlinkLeft", "x")
    values = np.array([0.25, 1.0, 0.0])
    builder = OscBundleBuilder(IMMEDIATELY)
    for name, value in zip(names, values):
        message = OscMessageBuilder(VAL_ADDRESS)
        message.add_arg(name, "s")
        message.add_arg(float(value), "f")
        builder.add_content(message.build())
    builder.add_content(OscMessageBuilder(APPLY_ADDRESS).build())
    assert VMCEncoder(names).encode(values) == [builder.build().dgram]


def test_non_finite_and_out_of_range_values_are_clipped():
    blend = BlendshapeMap(NAMES)
    x = np.full(16, np.nan)
    x[NAMES.index("jaw")] = 3.0
    x[NAMES.index("orbicularis_oris")] = -1.0
    values = blend(x)
    assert np.isfinite(values).all() and values.min() >= 0 and values.max() <= 1
    assert values[blend.names.index("jawOpen")] == 1.0 and values[blend.names.index("mouthPucker")] == 0.0


def test_custom_mapping_and_its_errors():
    blend = BlendshapeMap(NAMES, {"jaw": {"jawOpen": 0.5, "mouthClose": -0.2}}, case="pascal")
    assert blend.names == ("JawOpen", "MouthClose")
    x = np.zeros(16)
    x[NAMES.index("jaw")] = 1.0
    assert np.allclose(blend(x), [0.5, 0.0])
    with pytest.raises(InputError, match="mapping.nose"):
        BlendshapeMap(NAMES, {"nose": {"a": 1.0}})
    with pytest.raises(InputError, match="mapping.jaw.jawOpen"):
        BlendshapeMap(NAMES, {"jaw": {"jawOpen": "big"}})
    with pytest.raises(InputError, match="case"):
        BlendshapeMap(NAMES, case="shouting")


def test_defaults():
    out = VMCOutput(NAMES)
    assert out.address == ("127.0.0.1", DEFAULT_PORT)
    out.close()


@pytest.mark.parametrize("port", [0, -1, 65536, 99999, True, "39539", 1.5])
def test_a_port_outside_1_to_65535_is_an_error_naming_the_port(port):
    with pytest.raises(InputError) as info:
        VMCOutput(NAMES, port=port)
    assert info.value.field == "port" and "1..65535" in info.value.message


@pytest.mark.parametrize("host", ["", "   ", "0.0.0.0", "::", "255.255.255.255", "no such host.invalid"])
def test_a_host_that_is_not_one_receiver_is_an_error_naming_the_host(host):
    with pytest.raises(InputError) as info:
        VMCOutput(NAMES, host=host)
    assert info.value.field == "host"


def test_loopback_by_default_and_another_machine_only_when_named_and_announced(capsys):
    from types import SimpleNamespace

    from livebridge.cli.runtime import _announce_outputs

    with VMCOutput(NAMES) as local, VMCOutput(NAMES, host="192.0.2.7", port=9000) as remote, \
            VMCOutput(NAMES, host="localhost") as named:
        assert local.is_local and named.is_local and not remote.is_local
        assert local.describe() == f"VMC/OSC: sending to 127.0.0.1:{DEFAULT_PORT} on this machine"
        assert named.describe().endswith("(localhost) on this machine")
        assert "192.0.2.7:9000" in remote.describe() and "ANOTHER MACHINE" in remote.describe()
        _announce_outputs(SimpleNamespace(outputs=(remote,)))
        _announce_outputs(SimpleNamespace(outputs=()))
    assert capsys.readouterr().out == remote.describe() + "\n"


def test_a_send_the_network_refuses_is_dropped_and_kept_not_raised():
    class Refusing:
        def sendto(self, data, address):
            raise OSError(22, "Invalid argument")

        def close(self):
            pass

    out = VMCOutput(NAMES)
    out._socket.close()
    out._socket = Refusing()
    assert out.send_contractions(np.zeros(len(NAMES))) == 0
    assert out.dropped == 1 and out.last_error.errno == 22


@pytest.mark.parametrize("value,words", [("127.0.0.1:99999", "port"), ("127.0.0.1:0", "port"),
                                         ("0.0.0.0:39539", "host")])
def test_demo_vmc_option_is_checked_before_anything_starts(value, words):
    from click.testing import CliRunner

    from livebridge.cli import main

    result = CliRunner().invoke(main, ["demo", "--vmc", value, "--frames", "1", "--no-servo", "--no-render",
                                       "--size", "320x200", "--unpaced"])
    assert result.exit_code == 2 and "--vmc" in result.output and words in result.output

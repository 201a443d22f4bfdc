"""``livebridge sim`` / ``livebridge servo`` command lines."""

from __future__ import annotations

import subprocess
import sys

import pytest
from click.testing import CliRunner

from livebridge.cli import main
from livebridge.servo.rig import load_rig


def test_sim_dynamixel_prints_pty_first_and_serves_the_vendor_sdk():
    sdk = pytest.importorskip("dynamixel_sdk")
    command = [sys.executable, "-c", "from livebridge.cli import main; main()",
               "sim", "dynamixel", "--ids", "1-16", "--model", "XL330-M288"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        path = process.stdout.readline().strip()
        assert path.startswith("/dev/")
        from livebridge.drivers.dynamixel import sdk_port

        port = sdk_port(path, 2000.0)  # the simulator process may be slow to answer on a loaded machine
        assert port.openPort() and port.setBaudRate(1_000_000)
        ph = sdk.PacketHandler(2.0)
        assert ph.ping(port, 16) == (1200, 0, 0)
        port.closePort()
    finally:
        process.terminate()
        process.wait(timeout=10)
    assert process.returncode == 0


def test_help_on_every_level():
    runner = CliRunner()
    for args in (["servo", "--help"], ["servo", "scan", "--help"], ["servo", "jog", "--help"],
                 ["servo", "limits", "--help"], ["sim", "--help"], ["sim", "dynamixel", "--help"],
                 ["sim", "maestro", "--help"], ["sim", "ssc32", "--help"]):
        result = runner.invoke(main, args)
        assert result.exit_code == 0, (args, result.output)


def test_servo_scan_and_jog():
    runner = CliRunner()
    result = runner.invoke(main, ["servo", "scan", "simdynamixel://?ids=2-4&model=XM430-W350"])
    assert result.exit_code == 0, result.output
    lines = [line for line in result.output.splitlines() if "XM430" in line]
    assert [int(line.split()[0]) for line in lines] == [2, 3, 4]
    result = runner.invoke(main, ["servo", "jog", "simdynamixel://?ids=1&delay=0", "--id", "1", "--by", "100",
                                  "--speed", "1000"])
    assert result.exit_code == 0, result.output
    assert "to 2148" in result.output and "now at 2148" in result.output


def test_servo_limits_records_into_rig(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text('[buses.head]\nurl = "simdynamixel://?ids=1"\n'
                    '[servos.jaw]\nbus = "head"\nid = 1\nmuscles = { jaw = 1.0 }\nneutral = 2000\nmin = 1900\n'
                    'max = 2600\n')
    runner = CliRunner()
    result = runner.invoke(main, ["servo", "limits", str(path), "jaw", "--from-present", "neutral", "--max", "2500"])
    assert result.exit_code == 0, result.output
    jaw = load_rig(path).servo("jaw")
    assert (jaw.minimum, jaw.neutral, jaw.maximum) == (1900, 2048, 2500)
    result = runner.invoke(main, ["servo", "limits", str(path), "jaw", "--max", "7000"])
    assert result.exit_code != 0 and "jaw" in result.output

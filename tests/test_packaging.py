"""The distribution: folders install under livebridge.*, never as top-level packages."""

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_generic_top_level_names_are_not_importable(tmp_path):
    code = (
        "import importlib.util, sys\n"
        "missing = [n for n in ('drivers', 'calibration', 'simulators') if importlib.util.find_spec(n) is not None]\n"
        "import livebridge.drivers, livebridge.calibration, livebridge.simulators\n"
        "sys.exit(1 if missing else 0)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    result = subprocess.run([sys.executable, "-c", "import drivers"], cwd=tmp_path, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode != 0 and "ModuleNotFoundError" in result.stderr


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    # build from a copy, so the build leaves nothing (build/, *.egg-info) in the working tree
    source = tmp_path_factory.mktemp("source") / "livebridge"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(
        ".git", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache", ".ruff_cache", ".hypothesis", "out",
        "takes", ".docs"))
    out = tmp_path_factory.mktemp("wheel")
    result = subprocess.run([sys.executable, "-m", "build", "--wheel", "--outdir", str(out), str(source)],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    wheels = list(out.glob("livebridge-*.whl"))
    assert len(wheels) == 1
    with zipfile.ZipFile(wheels[0]) as archive:
        return set(archive.namelist())


def test_wheel_holds_the_subpackages_under_livebridge(wheel):
    for name in ("livebridge/__init__.py", "livebridge/drivers/__init__.py", "livebridge/simulators/__init__.py",
                 "livebridge/simulators/performer.py", "livebridge/calibration/__init__.py",
                 "livebridge/calibration/cameras.py", "livebridge/face/data/choe_ko_ict.toml",
                 "livebridge/face/builtin.py", "livebridge/devices/registry.py"):
        assert name in wheel, name
    top = {name.split("/")[0] for name in wheel}
    assert not top & {"drivers", "calibration", "simulators", "tests"}, top
    assert any(name.endswith("entry_points.txt") for name in wheel)

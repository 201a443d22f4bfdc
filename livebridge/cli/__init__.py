"""The ``livebridge`` command line.

Each command group lives in its own module of this package and is attached
here; heavy imports (OpenCV, scipy, hardware SDKs) happen inside the
commands, so ``livebridge --help`` stays fast and needs no device.
"""

from __future__ import annotations

import click

from livebridge import __version__
from livebridge.cli._attach import attach

# (module, attribute) of every command attached to the top-level group.
_COMMANDS = (
    ("livebridge.cli.basis", "basis"),
    ("livebridge.cli.markers", "markers"),
    ("livebridge.cli.calibrate", "calibrate"),
    ("livebridge.cli.cameras", "devices"),
    ("livebridge.cli.servo", "servo"),
    ("livebridge.cli.sim", "sim"),
    ("livebridge.cli.bench", "bench"),
    ("livebridge.cli.runtime", "run"),
    ("livebridge.cli.runtime", "demo"),
    ("livebridge.cli.take", "take"),
)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="livebridge")
def main() -> None:
    """Live facial motion capture to muscle contractions and animatronics."""


attach(main, _COMMANDS)

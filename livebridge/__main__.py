"""``python -m livebridge``: the same command line as the ``livebridge`` entry point."""

from livebridge.cli import main

main(prog_name="livebridge")

"""``python -m livebridge``: the same command line as the ``livebridge`` entry point."""

from livebridge.cli import main

if __name__ == "__main__":  # a spawned worker process imports this module again: it must not run the command
    main(prog_name="livebridge")

"""A camera node in its own process for the node tests: ``node_process.py PORT OFFSET_S DRIFT T_REF URL...``.

Like ``livebridge node``, plus an injected skewed clock (:class:`livebridge.nodes.node.SkewedClock`). Prints
the frame port on its first line, then serves until its stdin closes (the test ended or died) or it is killed.
"""

from __future__ import annotations

import sys


def main(argv: list[str]) -> None:
    from livebridge.devices.registry import open_cameras
    from livebridge.nodes.node import CameraNode, SkewedClock

    port, offset, drift, t_ref, *urls = argv
    sources = [source for url in urls for source in open_cameras(url)]
    clock = SkewedClock(float(offset), float(drift), float(t_ref))
    with CameraNode(sources, f"tcp://127.0.0.1:{port}", clock=clock) as node:
        node.name = f"node-{node.port}"  # as the host's status line names it
        print(node.port, flush=True)
        sys.stdin.read()  # until the test closes our stdin (or dies: then EOF too)


if __name__ == "__main__":
    main(sys.argv[1:])

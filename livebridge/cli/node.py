"""``livebridge node``: run a camera node, serving local cameras' marker centroids to a host over ZeroMQ."""

from __future__ import annotations

import signal
import sys
import threading

import click

from livebridge.cli._options import CameraURL, InputPath, allow_remote_option, bind_host_problem
from livebridge.errors import InputError

DEFAULT_ADDRESS = "tcp://127.0.0.1:7000"


def _address(value: str, allow_remote: bool) -> str:
    """``tcp://HOST:PORT`` checked: a port in 0..65534 (0: a free pair), loopback unless ``--allow-remote``."""
    scheme, _, rest = value.partition("://")
    host, _, port = rest.rpartition(":")
    if scheme != "tcp" or not host or not port.isdigit() or int(port) > 65534:
        raise click.BadParameter(f"{value!r} is not tcp://HOST:PORT with a port in 0..65534 (control on PORT + 1)",
                                 param_hint="--host")
    problem = bind_host_problem(host)
    if problem is not None and not allow_remote:
        raise click.BadParameter(problem.replace("the live face", "the camera stream"), param_hint="--host")
    return value


@click.command()
@allow_remote_option
@click.option("--cameras", "camera_urls", type=CameraURL(), multiple=True, required=True,
              help="Local camera URL(s) to serve, e.g. v4l2:///dev/video0 or sim://rig?cameras=8&camera=3.")
@click.option("--host", "address", default=DEFAULT_ADDRESS, show_default=True,
              help="tcp://HOST:PORT this node serves on (frames on PORT, control on PORT + 1); the host's "
                   "sources are node://HOST:PORT?camera=ID. Loopback unless --allow-remote.")
@click.option("--key", type=InputPath(), default=None,
              help="Shared key file (>= 32 secret bytes, the same on the host): CURVE encryption and authentication.")
@click.option("--name", default=None, help="The node's name in the host's status line (default: the address).")
def node(camera_urls: tuple[str, ...], address: str, key, name: str | None, allow_remote: bool) -> None:
    """Serve local cameras to a livebridge host: detect markers here, stream centroids, no images unless asked.

    Runs until Ctrl-C / SIGTERM. A host that restarts reconnects by itself, and so does this node's
    stream when the node restarts.
    """
    from livebridge.devices.registry import open_cameras
    from livebridge.nodes.keys import SharedKey
    from livebridge.nodes.node import CameraNode

    address = _address(address, allow_remote)
    shared = SharedKey.load(key) if key is not None else None
    sources = []
    for url in camera_urls:
        sources += open_cameras(url)
    ids = [s.source_id for s in sources]
    if len(set(ids)) != len(ids):
        raise InputError(f"two cameras share an id ({', '.join(ids)}); a node's camera ids must be unique",
                         field="--cameras")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    log = lambda line: click.echo(line, err=True)  # noqa: E731
    served = CameraNode(sources, address, shared, name=name or address, log=log)
    try:
        served.start()
    except served.zmq.ZMQError as error:  # the port is taken, the address is not this machine's (stopped)
        raise InputError(f"cannot serve on {address} (control on port + 1): {error}", field="--host") from None
    try:
        click.echo(f"tcp://{address.partition('://')[2].rpartition(':')[0]}:{served.port}")
        sys.stdout.flush()
        while not stop.wait(0.5):
            if served.ended and len(served.ended) == len(sources) and all(served.ended.values()):
                click.echo("every camera failed", err=True)
                break
    finally:
        served.stop()

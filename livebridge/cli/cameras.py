"""``livebridge devices``: the cameras and serial ports this machine can see."""

from __future__ import annotations

import json

import click


def _v4l2() -> list[dict]:
    from livebridge.drivers.v4l2 import list_devices

    return [{"path": d.path, "card": d.card, "driver": d.driver, "bus": d.bus, "by_id": list(d.by_id),
             "formats": [{"fourcc": f.fourcc, "description": f.description,
                          "modes": [[w, h, fps] for w, h, fps in f.modes]} for f in d.formats]}
            for d in list_devices()]


def _depthai() -> tuple[list[dict], str | None]:
    try:
        from livebridge.drivers.depthai import list_devices
    except ImportError as error:
        return [], f"depthai is not installed ({error})"
    try:
        return list_devices(), None
    except RuntimeError as error:
        return [], f"DepthAI search failed: {error}"


def _serial() -> list[dict]:
    from serial.tools import list_ports

    return [{"device": p.device, "description": p.description, "hwid": p.hwid} for p in list_ports.comports()]


@click.command()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text.")
def devices(as_json: bool) -> None:
    """List V4L2 cameras (by-id names, formats), DepthAI (OAK) devices and serial ports."""
    from livebridge.drivers.v4l2 import describe, list_devices

    v4l2 = list_devices()
    oak, oak_problem = _depthai()
    serial = _serial()
    if as_json:
        click.echo(json.dumps({"v4l2": _v4l2(), "depthai": oak, "serial": serial}))
        return
    click.echo("V4L2 cameras:")
    if v4l2:
        for device in v4l2:
            click.echo("  " + describe(device).replace("\n", "\n  "))
            click.echo(f"    url: v4l2://{device.by_id[0] if device.by_id else device.path}")
    else:
        click.echo("  none")
    click.echo("DepthAI (OAK) devices:")
    if oak:
        for device in oak:
            click.echo(f"  {device['id']}  {device['name']} ({device['platform']}, {device['protocol']}, "
                       f"{device['state']})  url: depthai://{device['id']}")
    else:
        click.echo(f"  none{f' ({oak_problem})' if oak_problem else ''}")
    click.echo("Serial ports:")
    if serial:
        for port in serial:
            click.echo(f"  {port['device']}  {port['description']} [{port['hwid']}]")
    else:
        click.echo("  none")

"""``livebridge bench NAME``: benchmarks against a named peer, last line JSON."""

from __future__ import annotations

import json

import click

from livebridge.bench import available_benchmarks, run_benchmark


@click.command()
@click.argument("name", required=False)
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON object on the last line.")
@click.option("--quick", is_flag=True, help="Smaller input, for a smoke test (figures are not the promised ones).")
def bench(name: str | None, as_json: bool, quick: bool) -> None:
    """Run benchmark NAME (omit NAME to list them)."""
    names = available_benchmarks()
    if name is None:
        for bench_name, summary in names.items():
            click.echo(f"{bench_name:14s} {summary}")
        return
    if name not in names:
        raise click.BadParameter(f"unknown benchmark {name!r}; known: {', '.join(names)}", param_hint="NAME")
    result = run_benchmark(name, quick=quick, log=click.echo if not as_json else lambda *_: None)
    if as_json:
        click.echo(json.dumps(result, sort_keys=True))
    else:
        for key, value in result.items():
            click.echo(f"{key}: {value}")

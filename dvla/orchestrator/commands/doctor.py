"""`dvla doctor [TOPOLOGY]`: can this host run the roles? One line per check, and the fix."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..doctor import CHECKS, exit_code, format_json, format_text, run_checks
from .common import Format, fail, topology_or_exit


def doctor(
    topology: Annotated[Optional[Path], typer.Argument(help="topology YAML: also check its ports, netns and remote nodes")] = None,
    format: Annotated[Format, typer.Option("--format", "-f", help="table or json")] = Format.table,
    skip: Annotated[list[str], typer.Option("--skip", help=f"leave a check out (repeatable): {', '.join(CHECKS)}")] = [],
) -> None:
    """Check this host: Vulkan for SAPIEN, torch and CUDA, SAPIEN's PhysX GPU library, zenoh, free
    ports, netns and tc, ssh to remote nodes, clock sync. Exits 1 when a required check fails."""
    unknown = [name for name in skip if name not in CHECKS]
    if unknown:
        raise fail(f"--skip: unknown check {unknown[0]!r} (expected one of {', '.join(CHECKS)})")
    topo = topology_or_exit(topology) if topology is not None else None
    progress = None if format == Format.json else (lambda name: typer.echo(f"checking {name} ...", err=True))
    results = run_checks(topo, progress, tuple(skip))
    host = os.uname().nodename
    if format == Format.json:
        typer.echo(format_json(results, {"host": host, "topology": str(topology) if topology else None}))
    else:
        where = f", topology {topology} (run {topo.run})" if topo is not None else ""
        typer.echo(format_text(results, f"dvla doctor: host {host}{where}"))
    code = exit_code(results)
    if code:
        raise typer.Exit(code)

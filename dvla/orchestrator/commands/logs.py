"""`dvla logs ROLE [-f]`: print (and follow) one role's log from the run directory."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from .common import RUNS_ROOT, fail


def logs(
    role: Annotated[str, typer.Argument(help="role name, e.g. rollout-node0-0 (prefix accepted)")],
    run: Annotated[Optional[str], typer.Option(help="run id (default: the newest run)")] = None,
    follow: Annotated[bool, typer.Option("--follow", "-f", help="keep printing new lines")] = False,
    lines: Annotated[int, typer.Option("--lines", "-n", help="last N lines")] = 50,
    runs: Annotated[Path, typer.Option(help="directory of run directories")] = RUNS_ROOT,
) -> None:
    """Show a role's log."""
    if run is None:
        dirs = sorted((p for p in runs.glob("*/logs") if p.is_dir()), key=lambda p: p.stat().st_mtime, reverse=True)
        if not dirs:
            raise fail(f"no run directory with logs under {runs}/")
        log_dir = dirs[0]
    else:
        log_dir = runs / run / "logs"
    matches = sorted(log_dir.glob(f"{role}*.log"))
    if not matches:
        known = ", ".join(p.stem for p in sorted(log_dir.glob("*.log")))
        raise fail(f"no log for role {role!r} in {log_dir} (known: {known or 'none'})")
    if len(matches) > 1 and not any(p.stem == role for p in matches):
        raise fail(f"role {role!r} is ambiguous: {', '.join(p.stem for p in matches)}")
    path = next((p for p in matches if p.stem == role), matches[0])
    with open(path, errors="replace") as f:
        for line in f.readlines()[-lines:]:
            typer.echo(line.rstrip("\n"))
        while follow:
            line = f.readline()
            if line:
                typer.echo(line.rstrip("\n"))
            else:
                time.sleep(0.2)

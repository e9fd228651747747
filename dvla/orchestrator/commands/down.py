"""`dvla down [RUN]`: stop a run started elsewhere and remove what it left (processes, netns)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..launcher import killpg
from ..netns import destroy_names
from ..run import pid_alive
from .common import RUNS_ROOT, find_run


def down(
    run: Annotated[Optional[str], typer.Argument(help="run id or topology file (default: the newest live run)")] = None,
    runs: Annotated[Path, typer.Option(help="directory of run directories")] = RUNS_ROOT,
    timeout: Annotated[float, typer.Option(help="seconds to wait for the orchestrator's clean stop before killing")] = 60.0,
) -> None:
    """Ask the run's orchestrator to stop (as Ctrl-C would); kill and clean up after `timeout`."""
    run_id, state = find_run(run, runs)
    pid = int(state.get("pid", 0))
    if pid and pid_alive(pid):
        os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        while pid_alive(pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        if pid_alive(pid):
            typer.echo(f"dvla: orchestrator {pid} did not stop in {timeout:.0f} s: killing", err=True)
            os.kill(pid, signal.SIGKILL)
    for child in state.get("children", {}).values():
        if pid_alive(int(child)):
            killpg(int(child), signal.SIGKILL)
    leftovers = state.get("netns") or []
    if leftovers:
        removed = destroy_names(run_id, leftovers)
        if removed:
            typer.echo(f"dvla: removed {', '.join(removed)}")
    state_file = runs / run_id / "state.json"
    if state_file.exists():
        state_file.unlink()
    typer.echo(f"dvla: run {run_id} is down")


"""`dvla up TOPOLOGY`: launch a run, show it live, stop at its budget; exit code = outcome."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..netns import NetnsError
from ..run import ExitCode, Up, UpOptions, install_sigint
from ..view import render_table
from .common import RUNS_ROOT, fail, topology_or_exit


def up(
    topology: Annotated[Path, typer.Argument(help="topology YAML file")],
    max_env_steps: Annotated[Optional[int], typer.Option(help="stop after this many learner env steps")] = None,
    until_success: Annotated[
        Optional[float], typer.Option(help="stop once eval success_once >= this for the topology's consecutive evals")
    ] = None,
    max_wall_s: Annotated[Optional[float], typer.Option(help="stop after this many seconds")] = None,
    mode: Annotated[Optional[str], typer.Option(help="async (swimlanes) or sync (lock-step baseline)")] = None,
    seed: Annotated[Optional[int], typer.Option(help="master seed (overrides the topology's)")] = None,
    base_port: Annotated[Optional[int], typer.Option(help="first TCP port of the run")] = None,
    runs: Annotated[Path, typer.Option(help="directory of run directories")] = RUNS_ROOT,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no live view; one line per 10 s")] = False,
) -> None:
    """Start every role of TOPOLOGY as its own process and supervise them until the run ends."""
    if mode is not None and mode not in ("async", "sync"):
        raise fail(f"--mode: expected async or sync, got {mode!r}")
    if max_env_steps is not None and max_env_steps < 1:
        raise fail(f"--max-env-steps: expected a positive integer, got {max_env_steps}")
    if until_success is not None and not 0 < until_success <= 1:
        raise fail(f"--until-success: expected a value in (0, 1], got {until_success}")
    topo = topology_or_exit(topology)
    opts = UpOptions(
        max_env_steps=max_env_steps, until_success=until_success, max_wall_s=max_wall_s,
        mode=mode, seed=seed, base_port=base_port, runs_root=runs,
    )
    live = sys.stdout.isatty() and not quiet
    last_line = [0.0]
    shown_events = [0]

    def tick(u: Up) -> None:
        for e in u.events[shown_events[0]:]:
            typer.echo(f"[dvla] {e}", err=True)
        shown_events[0] = len(u.events)
        m = u.monitor
        if m is None or m.last is None:
            return
        snap = m.last
        ev = m.evals[-1] if m.evals else None
        head = (
            f"{u.topo.run}  t={m.now():6.1f}s  env_steps={snap.env_steps}  steps/s={snap.steps_per_s:.0f}  "
            f"version={snap.version}  eval success_once={'-' if ev is None else f'{ev.success_once:.2f}'}"
        )
        if live:
            expected = [p.config.name for p in u.plan.processes]
            sys.stdout.write("\x1b[H\x1b[2J" + head + "\n\n" + render_table(snap.statuses, expected, {n: c.restarts for n, c in u.launcher.children.items()}) + "\n")
            sys.stdout.flush()
        elif time.monotonic() - last_line[0] >= 10:
            last_line[0] = time.monotonic()
            typer.echo(head)

    try:
        u = Up(topo, opts, on_tick=tick)
    except (RuntimeError, OSError, ValueError) as err:
        raise fail(str(err))
    install_sigint(u)
    typer.echo(f"dvla: run {u.topo.run} -> {u.run_dir}  ({len(u.plan.processes)} processes)")
    try:
        code = u.run()
    except NetnsError as err:  # the emulated cluster could not be built (it removed itself)
        raise fail(str(err), code=ExitCode.ROLE_FAILED)
    for e in u.events[shown_events[0]:]:
        typer.echo(f"[dvla] {e}", err=True)
    res = u.monitor.result() if u.monitor else {}
    typer.echo(
        f"dvla: run {u.topo.run} ended: {u.reason}; env_steps={res.get('env_steps')} "
        f"startup={_fmt(res.get('startup_s'))}s train={_fmt(res.get('train_s'))}s "
        f"steps/s={_fmt(res.get('train_steps_per_s'))}; results in {u.run_dir}"
    )
    if code not in (ExitCode.SUCCESS,):
        raise typer.Exit(code)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"

"""`dvla up TOPOLOGY`: launch a run, show it live, stop at its budget; exit code = outcome."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from ...config import BudgetConfig, range_problems
from ..netns import NetnsError
from ..run import ORCHESTRATOR_LOG, ExitCode, Up, UpOptions, install_sigint, start_detached
from ..slurm import SlurmError
from ..ssh import SshError
from ..view import render_table
from ..wandb_log import open_hint
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
    init_weights: Annotated[Optional[Path], typer.Option(
        help="warm start: the policy's tensors (safetensors) or a run's checkpoints directory (overrides task.init_weights)")
    ] = None,
    runs: Annotated[Path, typer.Option(help="directory of run directories")] = RUNS_ROOT,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no live view; one line per 10 s")] = False,
    resume: Annotated[bool, typer.Option("--resume", help="continue the run from its last checkpoint (error if none)")] = False,
    fresh: Annotated[bool, typer.Option("--fresh", help="delete the run directory (checkpoints included) and start over")] = False,
    detach: Annotated[
        bool, typer.Option("--detach", "-d", help="run in the background (log: RUN_DIR/orchestrator.log); return once the roles are started")
    ] = False,
) -> None:
    """Start every role of TOPOLOGY as its own process and supervise them until the run ends.

    An existing run directory is continued (from its last checkpoint); --fresh starts over."""
    if mode is not None and mode not in ("async", "sync"):
        raise fail(f"--mode: expected async or sync, got {mode!r}")
    for key, message in range_problems(BudgetConfig(max_env_steps=max_env_steps, until_success=until_success,
                                                    max_wall_s=max_wall_s)):
        raise fail(f"--{key.replace('_', '-')}: {message}")
    if init_weights is not None and not init_weights.exists():
        raise fail(f"--init-weights: not found: {init_weights} (expected a safetensors file or a checkpoints directory)")
    topo = topology_or_exit(topology)
    opts = UpOptions(
        max_env_steps=max_env_steps, until_success=until_success, max_wall_s=max_wall_s,
        mode=mode, seed=seed, base_port=base_port, runs_root=runs, resume=resume, fresh=fresh,
        init_weights=str(init_weights.resolve()) if init_weights is not None else None,
    )
    live = sys.stdout.isatty() and not quiet and not detach
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
            f"version={snap.version}  eval success_once="
            f"{'-' if ev is None else f'{ev.success_once:.2f} [{ev.success_low:.2f}, {ev.success_high:.2f}]'}"
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
    if detach:
        pid = start_detached(u, lambda: _run_to_end(u, shown_events))
        _report_detached(u, pid, runs)
        return
    install_sigint(u)
    code = _run_to_end(u, shown_events)
    if code not in (ExitCode.SUCCESS,):
        raise typer.Exit(code)


def _run_to_end(u: Up, shown_events: list[int]) -> int:
    """Run `u` in this process; print its events and a closing line; return its exit code."""
    typer.echo(f"dvla: run {u.topo.run} -> {u.run_dir}  ({len(u.plan.processes)} processes)")
    typer.echo(f"  tensorboard: tensorboard --logdir {u.run_dir / 'tb'}")
    if u.topo.logging.wandb is not None:
        typer.echo(f"  wandb: {open_hint(u.topo.logging.wandb, u.run_dir)}")
    try:
        code = u.run()
    except (NetnsError, SshError, SlurmError) as err:  # the cluster could not be built or reached (nothing is left)
        typer.echo(f"dvla: {err}", err=True)
        return ExitCode.ROLE_FAILED
    for e in u.events[shown_events[0]:]:
        typer.echo(f"[dvla] {e}", err=True)
    res = u.monitor.result() if u.monitor else {}
    typer.echo(
        f"dvla: run {u.topo.run} ended: {u.reason}; env_steps={res.get('env_steps')} "
        f"startup={_fmt(res.get('startup_s'))}s train={_fmt(res.get('train_s'))}s "
        f"steps/s={_fmt(res.get('train_steps_per_s'))}; results in {u.run_dir}"
    )
    return code


def _report_detached(u: Up, pid: int | None, runs: Path) -> None:
    """Tell the user where the background run is and how to follow and stop it (or why it died)."""
    log_path = u.run_dir / ORCHESTRATOR_LOG
    if pid is None:
        tail = log_path.read_text(errors="replace").splitlines()[-15:] if log_path.exists() else []
        for line in tail:
            typer.echo(f"  {line}", err=True)
        raise fail(f"run {u.topo.run} did not start; see {log_path}", code=ExitCode.ROLE_FAILED)
    runs_opt = "" if runs == RUNS_ROOT else f" --runs {runs}"
    run = u.topo.run
    first = u.plan.processes[0].config.name
    typer.echo(f"dvla: run {run} is up in the background (orchestrator pid {pid}) -> {u.run_dir}")
    typer.echo(f"  status:  dvla status {run}{runs_opt}")
    typer.echo(f"  tensorboard: tensorboard --logdir {u.run_dir / 'tb'}")
    if u.topo.logging.wandb is not None:
        typer.echo(f"  wandb: {open_hint(u.topo.logging.wandb, u.run_dir)}")
    typer.echo(f"  logs:    dvla logs {first} --run {run}{runs_opt} -f   (orchestrator: {log_path})")
    typer.echo(f"  stop:    dvla down {run}{runs_opt}")


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"

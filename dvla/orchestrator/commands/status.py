"""`dvla status [RUN]`: every role's state, policy version, lag, steps/s and lane utilisation.

Works from any terminal that can reach the run's control plane: it reads the run's state file
for the entry endpoints and the secret, collects every status reply, then renders it.
"""

from __future__ import annotations

import os
import queue
import sys
import threading
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from ...fabric.messages import RoleStatus
from ..run import state_fabric
from ..view import render_json, render_table
from .common import Format, RUNS_ROOT, fail, find_run


def status(
    run: Annotated[Optional[str], typer.Argument(help="run id or topology file (default: the newest live run)")] = None,
    format: Annotated[Format, typer.Option("--format", "-f", help="table or json")] = Format.table,
    runs: Annotated[Path, typer.Option(help="directory of run directories")] = RUNS_ROOT,
    timeout: Annotated[float, typer.Option(help="seconds to wait for replies")] = 2.0,
    connect_timeout: Annotated[float, typer.Option(help="seconds to keep trying to reach the control plane "
                                                        "(a run that has just ended is not there any more)")] = 15.0,
) -> None:
    """Show the live roles of a run."""
    if not (timeout > 0 and connect_timeout > 0):
        raise fail(f"--timeout ({timeout}) and --connect-timeout ({connect_timeout}) must be > 0")
    run_id, state = find_run(run, runs)
    replies, worker = _collect(run_id, state, timeout, connect_timeout)
    statuses = {msg.name: msg for _s, msg in replies}
    expected = sorted(p.stem for p in (runs / run_id / "roles").glob("*.json"))
    restarts = {k: int(v) for k, v in state.get("restarts", {}).items()}
    if format == Format.json:
        silent = sorted(set(expected) - set(statuses))
        typer.echo(render_json(statuses, {"run": run_id, "silent": silent, "restarts": restarts}))
    else:
        typer.echo(render_table(statuses, expected, restarts))
    _leave(worker, 0)


def _leave(worker: threading.Thread, code: int) -> None:
    """Give the session thread up to a second to close; if it is still inside Zenoh (a run ending
    under it), leave the process at once: interpreter shutdown under a thread in Zenoh's native
    code aborts the process, which would turn a printed answer into a crash."""
    worker.join(1.0)
    if worker.is_alive():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def _collect(run_id: str, state: dict, timeout: float,
             connect_timeout: float) -> tuple[list[tuple[str, RoleStatus]], threading.Thread]:
    """Every status reply, and the thread that holds the session. Opening the session is bounded by
    `connect_timeout`, querying by `timeout`: the session lives on a thread of its own, and a
    close that a run ending under it holds up is left to the process's exit (`_leave`)."""
    done: queue.Queue[tuple[str, Any]] = queue.Queue()

    def work() -> None:
        try:
            fabric = state_fabric(state, "status-cli", open_timeout_s=connect_timeout)
        except (ConnectionError, ValueError) as err:
            done.put(("error", f"control plane unreachable: {err}"))
            return
        try:
            done.put(("ok", fabric.query(fabric.keys.status_all(), expect=RoleStatus, timeout=timeout, droppable=True)))
        except Exception as err:  # reported as the command's error, not as a dead thread
            done.put(("error", f"status query failed: {err}"))
        finally:
            fabric.close()

    worker = threading.Thread(target=work, name="status-cli", daemon=True)
    worker.start()
    try:
        kind, got = done.get(timeout=connect_timeout + timeout + 1.0)  # +1: the open's last attempt
    except queue.Empty:
        kind, got = "error", f"no answer from the control plane within {connect_timeout + timeout:.0f} s"
    if kind == "error":
        exit_ = fail(f"run {run_id}: {got}")
        _leave(worker, exit_.exit_code)
        raise exit_
    return got, worker

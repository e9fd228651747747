"""`dvla identity issue|revoke`: credentials for producers outside the topology (a robot, a
user's own sampling loop), issued and revoked by the run's operator key."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import typer

from ...fabric.identity import REVOKED_FILE, Identity, IdentityError, read_revoked
from ...fabric.keys import check_name
from ...fabric.messages import Command
from ..run import state_fabric
from ..ssh import write_private
from .common import RUNS_ROOT, fail

app = typer.Typer(help="Credentials for producers outside the topology (docs/security.md).", no_args_is_help=True)

#: kinds an outside producer may be issued: never one that publishes weights or commands
ISSUABLE = ("rollout", "evaluator")


def _operator(run: str, runs: Path) -> Identity:
    path = runs / run / "operator.id"
    try:
        return Identity.from_text(path.read_text(), str(path))
    except FileNotFoundError:
        raise fail(f"{path}: no operator key (start the run once with `dvla up` to create it)")
    except OSError as err:
        raise fail(f"{path}: cannot read the operator key: {err.strerror or err}")
    except IdentityError as err:
        raise fail(str(err))


def _live_state(run: str, runs: Path) -> dict | None:
    state = runs / run / "state.json"
    return json.loads(state.read_text()) if state.exists() else None


@app.command("issue")
def issue(
    run: Annotated[str, typer.Argument(help="run id (its directory holds operator.id)")],
    name: Annotated[str, typer.Option(help="the producer's role name: the key suffix of its chunks")],
    output: Annotated[Path, typer.Option("--output", "-o", help="credential file to write (mode 0600)")],
    kind: Annotated[str, typer.Option(help=f"identity kind, one of {', '.join(ISSUABLE)}")] = "rollout",
    runs: Annotated[Path, typer.Option(help="directory of run directories")] = RUNS_ROOT,
) -> None:
    """Write a credential for `name`, certified by the run's operator key (format:
    docs/wire-format.md section 8); pass its text in DVLA_IDENTITY to the producer."""
    if kind not in ISSUABLE:
        raise fail(f"--kind {kind!r}: an outside producer may be one of {', '.join(ISSUABLE)}")
    try:
        check_name("role", name)
    except ValueError as err:
        raise fail(f"--name: {err}")
    operator = _operator(run, runs)
    state = _live_state(run, runs)
    if state is not None and name in state.get("children", {}):
        raise fail(f"--name {name!r} is a role of the running topology; pick another name")
    if name in read_revoked(runs / run):
        raise fail(f"--name {name!r} is revoked in {runs / run / REVOKED_FILE}; pick another name")
    write_private(output, operator.issue(kind, name).to_text() + "\n")
    typer.echo(f"dvla: wrote the {kind} credential of {name!r} for run {run!r} to {output}")


@app.command("revoke")
def revoke(
    run: Annotated[str, typer.Argument(help="run id")],
    name: Annotated[str, typer.Argument(help="the name whose credentials every role must refuse from now on")],
    runs: Annotated[Path, typer.Option(help="directory of run directories")] = RUNS_ROOT,
) -> None:
    """Refuse `name` for the rest of the run: recorded in the run directory (roles read it when
    they start) and, when the run is up, sent to every live role as a `revoke` command."""
    try:
        check_name("role", name)
    except ValueError as err:
        raise fail(f"{name!r}: {err}")
    _operator(run, runs)  # the run exists and has an operator
    path = runs / run / REVOKED_FILE
    names = read_revoked(runs / run) | {name}
    write_private(path, "".join(f"{n}\n" for n in sorted(names)))
    state = _live_state(run, runs)
    if state is None:
        typer.echo(f"dvla: {name!r} revoked in {path} (run {run!r} is not up)")
        return
    try:
        fabric = state_fabric(state, "operator", open_timeout_s=20.0)
    except (ValueError, ConnectionError) as err:
        raise fail(f"{name!r} revoked in {path}, but the live run was not told: {err}", code=1)
    try:
        cmd = Command(target="all", verb="revoke", args={"name": name}, issued_ns=time.time_ns())
        for _ in range(3):  # the tool's session may still be joining the ctrl plane's routes
            fabric.publish_ctrl(fabric.keys.cmd("all"), cmd)
            time.sleep(0.2)
    finally:
        fabric.close()
    typer.echo(f"dvla: {name!r} revoked in {path} and in every live role of run {run!r}")

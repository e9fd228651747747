"""`dvla join`: one rollout outside the topology's hosts (a robot, a workstation behind NAT),
started from a credential of `dvla identity issue`, as a Zenoh client that only dials out to the
run's routers: those given, or those the topology's nodes name with ``router:``
(docs/embedding.md, "A robot as a rollout").

It runs dvla's own rollout role (`python -m dvla.roles.rollout`, the process `dvla up` starts)
with a config built from the topology's plan: the task and replication settings of the run, the
credential's name, and client endpoints instead of the planned peer links.
"""

from __future__ import annotations

import dataclasses
import os
import socket
import sys
from pathlib import Path
from typing import Annotated

import typer

from ...config import PlaneEndpoints, RoleConfig, Topology
from ...fabric import load_secret
from ...fabric.errors import SecretError
from ...fabric.identity import IDENTITY_ENV, Identity, IdentityError, read_revoked
from ..plan import make_plan, router_endpoints
from .common import RUNS_ROOT, fail, topology_or_exit

#: seconds a router endpoint gets to accept a TCP connection before `dvla join` gives up
PROBE_TIMEOUT_S = 5.0


def read_credential(path: Path, topo: Topology) -> Identity:
    """The rollout credential in `path`, checked against the topology (one-line errors)."""
    try:
        ident = Identity.from_text(path.read_text(), str(path))
    except FileNotFoundError:
        raise fail(f"{path}: no such credential file (write one with `dvla identity issue`)")
    except OSError as err:
        raise fail(f"{path}: cannot read the credential: {err.strerror or err}")
    except IdentityError as err:
        raise fail(str(err))
    if ident.run != topo.run:
        raise fail(f"{path}: a credential of run {ident.run!r}, not of this topology's run {topo.run!r}")
    if ident.kind != "rollout":
        raise fail(f"{path}: the credential of {ident.kind} {ident.name!r}; `dvla join` runs a rollout "
                   f"(issue one with `dvla identity issue {topo.run} --kind rollout`)")
    return ident


def dial(topo: Topology, plane: str, given: list[str]) -> tuple[str, ...]:
    """The endpoints to dial for `plane`: those given, else the routers the topology names."""
    if given:
        return tuple(given)
    named = router_endpoints(make_plan(topo, "."), plane)
    if not named:
        raise fail(f"--connect-{plane}: give the {plane} plane's router endpoint (tcp/HOST:PORT); "
                   "the topology names no node `router:`")
    return named


def probe(plane: str, endpoint: str) -> None:
    """Fail with one line unless `endpoint` (``tcp/H:P`` or ``tls/H:P``) accepts a connection."""
    scheme, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if scheme not in ("tcp", "tls") or not host or not port.isdigit():
        raise fail(f"--connect-{plane} {endpoint!r}: expected tcp/HOST:PORT or tls/HOST:PORT")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=PROBE_TIMEOUT_S).close()
    except OSError as err:
        raise fail(f"--connect-{plane} {endpoint}: router unreachable: {err.strerror or err}", code=1)


def rollout_config(topo: Topology, ident: Identity, actor: str | None, ctrl: tuple[str, ...], data: tuple[str, ...],
                   run_dir: Path) -> RoleConfig:
    """The config `dvla up` would give a rollout of this topology, as `ident`'s name, shipping to
    `actor` (default: the first learner rank) through client links to `ctrl` and `data`."""
    plan = make_plan(topo, str(run_dir))
    names = {p.config.name for p in plan.processes}
    if ident.name in names:
        raise fail(f"credential name {ident.name!r} is a role of the topology; issue one under another name")
    actors = [p.config for p in plan.processes if p.config.kind == "actor"]
    if actor is None:
        target = actors[0]
    else:
        found = [a for a in actors if a.name == actor]
        if not found:
            raise fail(f"--actor {actor!r}: not an actor of the topology ({', '.join(a.name for a in actors)})")
        target = found[0]
    tls_planes = topo.tls.planes if topo.tls is not None else ()
    return dataclasses.replace(
        target, name=ident.name, kind="rollout", node="outside", rack="outside", seed=topo.seed * 1000 + len(plan.processes),
        run_dir=str(run_dir),
        ctrl=PlaneEndpoints(mode="client", connect=ctrl, tls=topo.tls if "ctrl" in tls_planes else None),
        data=PlaneEndpoints(mode="client", connect=data, tls=topo.tls if "data" in tls_planes else None),
        parent=target.name, ancestors=(target.name,), children=(), actors=(target.name,), rollouts=(),
        cpus=None, lane_cpus=None, sim_workers=0, node_rollouts=1, group=None, eval_shard=(0, 1), lockstep_steps=0,
        report_ledger=True,  # its counter file is on this machine: the learner keeps the run's copy
    )


def join(
    topology: Annotated[Path, typer.Argument(help="the run's topology YAML")],
    credential: Annotated[Path, typer.Option(help="rollout credential from `dvla identity issue` (mode 0600)")],
    secret: Annotated[Path | None, typer.Option(help="the run's secret file (default: RUNS/RUN/secret)")] = None,
    connect_ctrl: Annotated[list[str], typer.Option(
        help="ctrl-plane router endpoint, e.g. tcp/H:P (repeatable; default: the topology's routers)")] = [],  # noqa: B006
    connect_data: Annotated[list[str], typer.Option(
        help="data-plane router endpoint, e.g. tcp/H:P (repeatable; default: the topology's routers)")] = [],  # noqa: B006
    actor: Annotated[str | None, typer.Option(help="the learner rank to ship to (default: the first)")] = None,
    runs: Annotated[Path, typer.Option(help="directory of run directories (counter files and logs go in RUNS/RUN)")] = RUNS_ROOT,
) -> None:
    """Run one rollout of TOPOLOGY's run from an issued credential, outside the topology's hosts,
    as a Zenoh client of the routers; it ships to a learner like any rollout and reconnects when
    its link comes back. Runs until stopped (Ctrl-C, SIGTERM, or the run's `dvla down`)."""
    topo = topology_or_exit(topology)
    ident = read_credential(credential, topo)
    run_dir = runs / topo.run
    if ident.name in read_revoked(run_dir):
        raise fail(f"{credential}: {ident.name!r} is revoked in {run_dir / 'revoked'}")
    if topo.mode != "async":
        raise fail(f"{topology}: mode {topo.mode!r}: only an async run takes rollouts from outside its plan")
    ctrl = dial(topo, "ctrl", connect_ctrl)
    data = dial(topo, "data", connect_data)
    try:
        key = load_secret(str(secret if secret is not None else run_dir / "secret"))
    except SecretError as err:
        raise fail(f"--secret: {err}")
    for plane, eps in (("ctrl", ctrl), ("data", data)):
        for ep in eps:
            probe(plane, ep)
    cfg = rollout_config(topo, ident, actor, ctrl, data, run_dir)
    config_path = run_dir / "roles" / f"{cfg.name}.json"
    config_path.parent.mkdir(parents=True, exist_ok=True)
    config_path.write_text(cfg.to_json())
    env = {**os.environ, IDENTITY_ENV: ident.to_text(), cfg.secret_env: key.hex()}
    typer.echo(f"dvla: {ident.name} joins run {topo.run!r} through ctrl {', '.join(ctrl)} and data {', '.join(data)}",
               err=True)
    sys.stdout.flush()
    # The rollout replaces this process: signals reach it directly, its exit status is ours.
    os.execve(sys.executable, [sys.executable, "-m", "dvla.roles.rollout", "--config", str(config_path)], env)

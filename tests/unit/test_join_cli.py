"""Tests of `dvla join` (a rollout outside the topology's hosts, from an issued credential): its
one-line refusals, and the rollout config it builds from the topology's plan."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from dvla.fabric.identity import Identity
from dvla.orchestrator.cli import app
from dvla.orchestrator.commands.join import rollout_config
from dvla.orchestrator.ssh import write_private
from dvla.orchestrator.topology import load_topology

runner = CliRunner()
RUN = "joinrun"

TOPOLOGY = f"""
run: {RUN}
task:
  env: "examples.embed_gym_loop:make_pendulum"
  policy: mlp
  envs_per_rollout: 2
  chunk_steps: 10
  device: cpu
racks:
  - name: rack0
    nodes:
      - name: node0
        host: localhost
        roles:
          - role: actor
          - role: rollout
"""


@pytest.fixture
def setup(tmp_path: Path) -> tuple[Path, Path, Identity]:
    """(topology file, runs directory, the run's operator) with a secret in the run directory."""
    topo = tmp_path / "t.yaml"
    topo.write_text(TOPOLOGY)
    runs = tmp_path / "runs"
    (runs / RUN).mkdir(parents=True)
    write_private(runs / RUN / "secret", "ab" * 32 + "\n")
    return topo, runs, Identity.operator(RUN)


def _cred(tmp_path: Path, ident: Identity, name: str = "cred.id") -> Path:
    path = tmp_path / name
    write_private(path, ident.to_text() + "\n")
    return path


def _join(topo: Path, runs: Path, cred: Path, *extra: str):
    return runner.invoke(app, ["join", str(topo), "--credential", str(cred), "--runs", str(runs), *extra])


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed once the block ends: nobody listens there


def test_join_refuses_missing_foreign_and_wrong_kind_credentials(setup, tmp_path):
    topo, runs, op = setup
    eps = ["--connect-ctrl", "tcp/127.0.0.1:1", "--connect-data", "tcp/127.0.0.1:2"]
    res = _join(topo, runs, tmp_path / "none.id", *eps)
    assert res.exit_code == 2 and "none.id: no such credential file" in res.output, res.output
    other = _cred(tmp_path, Identity.operator("otherrun").issue("rollout", "robot-1"), "other.id")
    res = _join(topo, runs, other, *eps)
    assert res.exit_code == 2 and "a credential of run 'otherrun', not of this topology's run 'joinrun'" in res.output
    ev = _cred(tmp_path, op.issue("evaluator", "robot-1"), "ev.id")
    res = _join(topo, runs, ev, *eps)
    assert res.exit_code == 2 and "the credential of evaluator 'robot-1'; `dvla join` runs a rollout" in res.output
    junk = tmp_path / "junk.id"
    junk.write_text("not a credential\n")
    res = _join(topo, runs, junk, *eps)
    assert res.exit_code == 2 and "not a dvla identity credential" in res.output
    assert len(res.output.strip().splitlines()) == 1


def test_join_refuses_a_revoked_or_planned_name(setup, tmp_path):
    topo, runs, op = setup
    eps = ["--connect-ctrl", "tcp/127.0.0.1:1", "--connect-data", "tcp/127.0.0.1:2"]
    (runs / RUN / "revoked").write_text("robot-9\n")
    res = _join(topo, runs, _cred(tmp_path, op.issue("rollout", "robot-9")), *eps)
    assert res.exit_code == 2 and "'robot-9' is revoked" in res.output, res.output
    with pytest.raises(typer.Exit):  # the planned rollout's own name
        rollout_config(load_topology(topo), op.issue("rollout", "rollout-node0-0"), None, ("tcp/a:1",), ("tcp/a:2",),
                       runs / RUN)


def test_join_needs_router_endpoints_that_answer(setup, tmp_path):
    topo, runs, op = setup
    cred = _cred(tmp_path, op.issue("rollout", "robot-1"))
    res = _join(topo, runs, cred, "--connect-data", "tcp/127.0.0.1:2")
    assert res.exit_code == 2 and "--connect-ctrl: give the ctrl plane's router endpoint" in res.output, res.output
    res = _join(topo, runs, cred, "--connect-ctrl", "udp/127.0.0.1:5", "--connect-data", "tcp/127.0.0.1:2")
    assert res.exit_code == 2 and "expected tcp/HOST:PORT" in res.output, res.output
    port = _closed_port()
    res = _join(topo, runs, cred, "--connect-ctrl", f"tcp/127.0.0.1:{port}", "--connect-data", "tcp/127.0.0.1:2")
    assert res.exit_code == 1 and f"--connect-ctrl tcp/127.0.0.1:{port}: router unreachable" in res.output, res.output
    assert not (runs / RUN / "roles" / "robot-1.json").exists()  # nothing started


def test_join_builds_the_planned_rollout_config_as_a_client_of_the_routers(setup):
    topo_path, runs, op = setup
    topo = load_topology(topo_path)
    cfg = rollout_config(topo, op.issue("rollout", "robot-1"), None, ("tcp/edge:7447",), ("tcp/edge:7448",), runs / RUN)
    assert (cfg.name, cfg.kind, cfg.run) == ("robot-1", "rollout", RUN)
    assert (cfg.ctrl.mode, cfg.ctrl.connect, cfg.ctrl.listen) == ("client", ("tcp/edge:7447",), ())
    assert (cfg.data.mode, cfg.data.connect, cfg.data.listen) == ("client", ("tcp/edge:7448",), ())
    assert (cfg.parent, cfg.ancestors, cfg.actors) == ("actor-node0-0", ("actor-node0-0",), ("actor-node0-0",))
    assert (cfg.rollouts, cfg.children, cfg.group, cfg.cpus) == ((), (), None, None)
    assert cfg.task == topo.task and cfg.replication == topo.replication
    with pytest.raises(typer.Exit):  # not an actor of the topology
        rollout_config(topo, op.issue("rollout", "robot-1"), "actor-x", ("tcp/e:1",), ("tcp/e:2",), runs / RUN)


def test_join_dials_the_routers_the_topology_names(setup, tmp_path):
    topo, runs, op = setup
    port = _closed_port()
    topo.write_text(TOPOLOGY + f"        router: {{ctrl: {port}, data: {port + 1}}}\n")
    res = _join(topo, runs, _cred(tmp_path, op.issue("rollout", "robot-1")))
    assert res.exit_code == 1 and f"--connect-ctrl tcp/127.0.0.1:{port}: router unreachable" in res.output, res.output

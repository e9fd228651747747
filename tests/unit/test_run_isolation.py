"""Two runs on one machine stay apart: a run whose listen ports another process holds refuses to
start with one line (its roles would otherwise join that run's planes, and each run's chunk
ledger would count the other's traffic)."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from benchmarks.ports import free_port_block

from dvla.orchestrator.launcher import busy_ports
from dvla.orchestrator.plan import make_plan
from dvla.orchestrator.run import Up, UpOptions
from dvla.orchestrator.topology import load_topology

ROOT = Path(__file__).resolve().parents[2]


def _listener() -> socket.socket:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen()
    return s


def test_a_held_base_port_refuses_the_run_naming_port_and_role(tmp_path: Path) -> None:
    with _listener() as other_run:
        port = other_run.getsockname()[1]
        with pytest.raises(ValueError) as err:
            Up(load_topology(str(ROOT / "topologies" / "tiny.yaml")), UpOptions(base_port=port, runs_root=tmp_path))
    line = str(err.value)
    assert "\n" not in line and f"port {port} (actor-node0-0's ctrl plane) is in use" in line and "--base-port" in line
    assert not (tmp_path / "tiny" / "secret").exists()  # refused before anything of the run was written


def test_busy_ports_lists_exactly_the_held_endpoints(tmp_path: Path) -> None:
    plan = make_plan(load_topology(str(ROOT / "topologies" / "tiny.yaml")), str(tmp_path), base_port=free_port_block())
    assert busy_ports(list(plan.processes)) == []
    data = plan.by_name("actor-node0-0").config.data.listen[0]
    port = int(data.rsplit(":", 1)[1])
    with socket.socket() as held:  # another run's actor, listening on this run's data port
        held.bind(("127.0.0.1", port))
        held.listen()
        assert busy_ports(list(plan.processes)) == [
            f"port {port} (actor-node0-0's data plane) is in use on this host (another run?): "
            "pass --base-port or change base_port"]

"""Names and addresses of `emulate: netns` (dvla.orchestrator.netns): pure functions, no root."""

from __future__ import annotations

from pathlib import Path

import pytest

from dvla.orchestrator.netns import (
    HOST_IP,
    SUBNET,
    NetnsWrapper,
    fabric_name,
    host_link_name,
    netns_name,
    node_ip,
    node_port,
    run_prefix,
    uplink_ends,
)
from dvla.orchestrator.plan import make_plan
from dvla.orchestrator.topology import load_topology

TOPOLOGIES = Path(__file__).resolve().parents[2] / "topologies"


def test_node_ip_is_stable_and_inside_the_fabric() -> None:
    assert node_ip(0, 0) == "10.77.0.10"
    assert node_ip(3, 2) == "10.77.3.12"
    ips = {node_ip(r, n) for r in range(255) for n in range(244)}
    assert len(ips) == 255 * 244 and HOST_IP not in ips
    assert all(ip.startswith("10.77.") for ip in ips)
    assert SUBNET.prefixlen == 16


@pytest.mark.parametrize("rack,node", [(-1, 0), (255, 0), (0, 244), (0, -1)])
def test_node_ip_rejects_out_of_range(rack: int, node: int) -> None:
    with pytest.raises(ValueError):
        node_ip(rack, node)


def test_names_fit_interface_limits_and_carry_the_run_prefix() -> None:
    run = "a-very-long-run-identifier-with-40-chars"
    prefix = run_prefix(run)
    assert prefix.startswith("dv-") and len(prefix) == 10
    names = [netns_name(run, f"node{i}") for i in range(200)] + [fabric_name(run), host_link_name(run)]
    assert all(n.startswith(prefix) and len(n) <= 15 for n in names)
    assert len(set(names)) == len(names)
    assert netns_name(run, "node0") == netns_name(run, "node0")
    assert netns_name("other", "node0") != netns_name(run, "node0")
    assert all(len(x) <= 15 for x in (node_port(254, 243), *uplink_ends(254)))


def test_plan_places_every_process_in_its_node_namespace(tmp_path: Path) -> None:
    topo = load_topology(TOPOLOGIES / "8node.yaml")
    plan = make_plan(topo, str(tmp_path))
    assert plan.addresses["r0n0"] == "10.77.0.10" and plan.addresses["r1n3"] == "10.77.1.13"
    for p in plan.processes:
        assert p.netns == netns_name(topo.run, p.config.node)
    actor = plan.by_name(plan.root_actor)
    argv = NetnsWrapper()(actor, ["python", "-m", "x"])
    assert argv == ["ip", "netns", "exec", actor.netns, "python", "-m", "x"]
    assert plan.ctrl_entry[0].startswith("tcp/10.77.0.10:")

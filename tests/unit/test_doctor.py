"""`dvla doctor` logic without the slow probes: outcomes, needs from a topology, the port check
against a real bound socket, parsers of tool output, and both renderings."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

import pytest

from dvla.orchestrator.doctor import (
    PHYSX_GPU_PROBE,
    CheckResult,
    Needs,
    check_cpus,
    check_ports,
    exit_code,
    format_json,
    format_text,
    needs_of,
    outcome,
    parse_device_summary,
    parse_ntp,
    physx_gpu_result,
)
from dvla.orchestrator.topology import parse_topology

TOPO = """
run: doc
base_port: {port}
emulate: {emulate}
racks:
  - name: r0
    nodes:
      - name: n0
        {address}
        roles: [{{role: actor}}, {{role: replicator}}, {{role: rollout}}]
      - name: n1
        host: {far}
        roles: [{{role: rollout}}]
"""


def _topo(port: int = 17400, emulate: str = "none", far: str = "localhost", address: str = ""):
    return parse_topology(TOPO.format(port=port, emulate=emulate, far=far, address=address), "doc.yaml")


def test_outcome_required_failure_fails_and_optional_one_warns() -> None:
    assert outcome("x", True, "fine", required=True).status == "ok"
    assert outcome("x", False, "broken", fix="do it", required=True).status == "fail"
    warn = outcome("x", False, "broken", fix="do it", required=False)
    assert warn.status == "warn" and warn.fix == "do it"
    assert outcome("x", True, "fine", fix="unused", required=False).fix is None


def test_exit_code_fails_only_on_fail() -> None:
    ok = CheckResult(name="a", status="ok", detail="")
    assert exit_code([ok, CheckResult(name="b", status="warn", detail=""), CheckResult(name="c", status="skip", detail="")]) == 0
    assert exit_code([ok, CheckResult(name="d", status="fail", detail="", required=True)]) == 1


def test_text_shows_fix_under_each_problem_and_a_verdict() -> None:
    results = [
        CheckResult(name="torch", status="ok", detail="torch 2.x", fix=None),
        CheckResult(name="vulkan", status="fail", detail="no device", fix="bash scripts/setup.sh system", required=True),
        CheckResult(name="clock", status="warn", detail="not synced", fix="timedatectl set-ntp true"),
        CheckResult(name="ssh", status="skip", detail="no remote nodes"),
    ]
    text = format_text(results, "dvla doctor: host h")
    lines = text.splitlines()
    assert lines[0] == "dvla doctor: host h"
    fail_at = next(i for i, l in enumerate(lines) if "FAIL" in l)
    assert "vulkan" in lines[fail_at] and "fix: bash scripts/setup.sh system" in lines[fail_at + 1]
    warn_at = next(i for i, l in enumerate(lines) if "WARN" in l)
    assert "fix: timedatectl set-ntp true" in lines[warn_at + 1]
    assert lines[-1] == "1 ok, 1 warning(s), 1 failure(s), 1 skipped: a required check failed"


def test_json_lists_every_check() -> None:
    results = [CheckResult(name="a", status="ok", detail="d"), CheckResult(name="b", status="warn", detail="e", fix="f")]
    doc = json.loads(format_json(results, {"host": "h"}))
    assert doc["host"] == "h" and doc["ok"] is True
    assert [c["name"] for c in doc["checks"]] == ["a", "b"] and doc["checks"][1]["fix"] == "f"


def test_needs_from_topology() -> None:
    assert needs_of(None).simulator and not needs_of(None).topology
    n = needs_of(_topo(port=20000))
    assert n.topology and n.simulator and not n.netns and n.remote_nodes == ()
    assert ("actor-n0-0", "tcp/127.0.0.1:20000") in n.endpoints
    remote = needs_of(_topo(far="gpu-7.lab", address="address: 10.1.2.3"))
    assert remote.remote_nodes == ("n1",)
    assert all("gpu-7.lab" not in ep for _r, ep in remote.endpoints)  # only this host's planes
    assert needs_of(_topo(emulate="netns")).netns


def _free_port_pair() -> int:
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            p = s.getsockname()[1]
        if p + 3 < 65000:
            return p
    raise RuntimeError("no port")


def test_port_check_passes_on_free_ports_and_fails_on_a_bound_one() -> None:
    port = _free_port_pair()
    assert check_ports(needs_of(_topo(port=port))).status == "ok"
    with socket.socket() as holder:
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        holder.bind(("127.0.0.1", port + 1))  # the actor's data port
        holder.listen(1)
        r = check_ports(needs_of(_topo(port=port)))
    assert r.status == "fail" and r.required
    assert f"{port + 1} (actor-n0-0" in r.detail and "--base-port" in (r.fix or "")


def test_port_check_names_an_address_this_host_lacks() -> None:
    r = check_ports(needs_of(_topo(address="address: 192.0.2.77", far="gpu-7.lab")))
    assert r.status == "fail" and "192.0.2.77" in r.detail


def test_port_check_skips_without_topology_and_inside_netns() -> None:
    assert check_ports(needs_of(None)).status == "skip"
    assert check_ports(needs_of(_topo(emulate="netns"))).status == "skip"


SAPIEN_SUMMARY = """GPU: llvmpipe (LLVM 15.0.6, 256 bits)
  Supported: 1
  Present:   0
  cudaId:    -1
GPU: Broken Card
  Supported: 0
"""


@pytest.mark.parametrize(
    "text, devices",
    [(SAPIEN_SUMMARY, ["llvmpipe (LLVM 15.0.6, 256 bits)"]), ("", []), ("GPU: X\n  Supported: 0\n", [])],
)
def test_parse_device_summary(text: str, devices: list[str]) -> None:
    assert parse_device_summary(text) == devices


def test_parse_ntp() -> None:
    assert parse_ntp("yes\n") is True and parse_ntp("no") is False and parse_ntp("") is None


PINNED = """
run: pin
racks:
  - name: r0
    nodes:
      - name: n0
        address: 192.0.2.8
        cpus: [{node}]
        roles: [{{role: actor}}, {{role: rollout, count: 2, lane_cpus: {{sim: [{lane}]}}}}]
      - name: far
        host: gpu-7.lab
        address: 192.0.2.9
        cpus: [63]
        roles: [{{role: rollout}}]
"""


def test_cpus_check_names_the_node_role_and_key_of_a_core_this_host_lacks() -> None:
    import os

    from dvla.orchestrator.plan import pinning_problems

    usable = sorted(os.sched_getaffinity(0))
    good = parse_topology(PINNED.format(node=usable[0], lane=usable[-1]), "pin.yaml")
    assert pinning_problems(good) == []  # the remote node's core 63 is not ours to check
    r = check_cpus(good)
    assert r.status == "ok" and r.required and "3 pinned" in r.detail  # the actor and both rollouts

    missing = max(usable) + 100
    bad = parse_topology(PINNED.format(node=usable[0], lane=missing), "pin.yaml")
    problems = pinning_problems(bad)
    assert problems == [f"node n0, role rollout: lane_cpus.sim names core(s) {missing}, which this host does not "
                        f"have (usable cores: {','.join(map(str, usable))})"]  # once, not per rollout process
    r = check_cpus(bad)
    assert r.status == "fail" and r.detail == problems[0]
    assert r.fix == "pin to cores this host has (nproc; taskset -pc $$ shows the usable ones)"
    assert pinning_problems(bad, allowed={usable[0], missing}) == []
    assert check_cpus(None).status == "skip"
    assert check_cpus(_topo()).status == "skip"  # nothing pinned


def test_physx_gpu_library_is_checked_only_where_cuda_is_and_a_missing_one_names_the_path_and_the_way_out() -> None:
    info = {"cuda": False, "version": "105.1-physx-5.3.1.patch0", "present": False,
            "path": "/root/.sapien/physx/105.1-physx-5.3.1.patch0/libPhysXGpu_64.so"}
    assert physx_gpu_result(info, Needs()).status == "skip"
    missing = physx_gpu_result(info, Needs(cuda=True))  # the topology asks for CUDA: checked even here
    assert missing.status == "warn" and not missing.required  # online hosts download it at first use
    assert info["path"] in missing.detail and "GitHub" in missing.detail
    assert "into /root/.sapien/physx/105.1-physx-5.3.1.patch0," in missing.fix and "sim_backend: physx_cpu" in missing.fix
    assert physx_gpu_result({**info, "cuda": True}, Needs()).status == "warn"
    assert physx_gpu_result({**info, "cuda": True, "present": True}, Needs()).status == "ok"


def test_physx_gpu_probe_answers_on_this_host() -> None:
    """The probe itself runs against the installed sapien and torch and says what this host has."""
    p = subprocess.run([sys.executable, "-c", PHYSX_GPU_PROBE], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    info = json.loads(p.stdout.strip().splitlines()[-1])
    assert set(info) == {"cuda", "version", "path", "present"}
    assert info["path"].endswith(f"/.sapien/physx/{info['version']}/libPhysXGpu_64.so")

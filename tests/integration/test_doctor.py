"""`dvla doctor` for real on this machine, as a user runs it: real imports, SAPIEN's device query,
a throwaway network namespace, real port binds."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import torch

from .test_up_e2e import ROOT, free_port_block

CHECKS = ["python", "torch", "cuda", "zenoh", "vulkan", "maniskill", "physx-gpu", "transformers", "libero", "ports", "cpus", "netns", "ssh", "clock"]


def _doctor(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dvla", "doctor", *args], cwd=ROOT, capture_output=True, text=True, timeout=300)


def _netns_usable() -> bool:
    return os.geteuid() == 0 and shutil.which("ip") is not None and shutil.which("tc") is not None


def test_doctor_json_with_a_topology_whose_port_is_taken(tmp_path: Path) -> None:
    port = free_port_block()
    topo = tmp_path / "t.yaml"
    topo.write_text((ROOT / "topologies" / "tiny.yaml").read_text() + f"\nbase_port: {port}\n")
    with socket.socket() as holder:  # the root actor's ctrl port
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        holder.bind(("127.0.0.1", port))
        holder.listen(1)
        proc = _doctor(str(topo), "--format", "json")
    assert proc.returncode == 1, proc.stdout + proc.stderr
    doc = json.loads(proc.stdout)
    by_name = {c["name"]: c for c in doc["checks"]}
    assert list(by_name) == CHECKS
    assert doc["ok"] is False and doc["topology"] == str(topo)
    assert all(c["status"] in ("ok", "warn", "fail", "skip") for c in doc["checks"])
    ports = by_name["ports"]
    assert ports["status"] == "fail" and f"{port} (actor-node0-0" in ports["detail"] and ports["fix"]
    # what this test suite itself relies on must be found healthy
    for name in ("python", "torch", "zenoh", "maniskill", "transformers"):
        assert by_name[name]["status"] == "ok", by_name[name]
    assert by_name["ssh"]["status"] == "skip"  # tiny has no remote node
    if not torch.cuda.is_available():  # nothing asks for CUDA here: the PhysX GPU library is not looked for
        assert by_name["physx-gpu"]["status"] == "skip", by_name["physx-gpu"]
    if _netns_usable():
        assert by_name["netns"]["status"] == "ok", by_name["netns"]
    assert not [n for n in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout.split()
                if n.startswith("dvdoc")]


def test_doctor_table_without_topology() -> None:
    proc = _doctor()
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("dvla doctor: host ")
    statuses = {line.split()[1]: line.split()[0] for line in lines[1:-1] if line.split() and line.split()[0] in ("ok", "WARN", "FAIL", "skip")}
    assert list(statuses) == CHECKS
    assert statuses["ports"] == "skip" and statuses["ssh"] == "skip"
    for i, line in enumerate(lines):
        if line.split() and line.split()[0] in ("WARN", "FAIL"):
            assert lines[i + 1].strip().startswith("fix: "), line
    assert proc.returncode == (1 if "FAIL" in statuses.values() else 0), proc.stdout
    assert "failure(s)" in lines[-1]

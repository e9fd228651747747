"""`emulate: netns` end to end at the network level: build a 2-rack x 2-node cluster, check every
link's token bucket against the configured rates (as tc holds them), move TCP traffic within a rack
and across racks (its throughput printed, not asserted: a measured figure), then tear it down and
check that nothing of the run is left. Needs root and `ip netns`."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time

import pytest

from dvla.orchestrator.netns import NODE_IF, NetnsCluster, node_port, run_prefix, uplink_ends
from dvla.orchestrator.plan import make_plan
from dvla.orchestrator.topology import parse_topology

NODE_GBIT = 0.2
UPLINK_GBIT = 0.05
PAYLOAD = 8 * 1024 * 1024
PORT = 5201


def _netns_usable() -> bool:
    if os.geteuid() != 0 or shutil.which("ip") is None or shutil.which("tc") is None:
        return False
    return subprocess.run(["ip", "netns", "list"], capture_output=True).returncode == 0


pytestmark = [
    pytest.mark.netns,
    pytest.mark.skipif(not _netns_usable(), reason="needs root and `ip netns`"),
]

TOPOLOGY = f"""
run: nstest-{os.getpid()}
emulate: netns
links:
  node_gbit: {NODE_GBIT}
  rack_uplink_gbit: {UPLINK_GBIT}
racks:
  - name: ra
    nodes:
      - name: ra0
        roles: [{{role: actor}}]
      - name: ra1
        roles: [{{role: rollout}}]
  - name: rb
    nodes:
      - name: rb0
        roles: [{{role: rollout}}]
      - name: rb1
        roles: [{{role: rollout}}]
"""

# Receiver: prints "ready", then the bytes received after the first read and the seconds they
# took (timing from the first byte leaves out connection setup and the token bucket's burst).
RECEIVER = """
import socket, sys, time
ip, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
srv = socket.socket()
srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
srv.bind((ip, port))
srv.listen(1)
srv.settimeout(20)
print("ready", flush=True)
conn, _ = srv.accept()
conn.settimeout(20)
first = conn.recv(1 << 20)
t0 = time.perf_counter()
got = 0
while len(first) + got < n:
    chunk = conn.recv(1 << 20)
    if not chunk:
        break
    got += len(chunk)
print(got, time.perf_counter() - t0, flush=True)
"""

SENDER = """
import socket, sys, time
ip, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
deadline = time.monotonic() + 5
while True:
    try:
        sock = socket.create_connection((ip, port), timeout=5)
        break
    except OSError:
        if time.monotonic() > deadline:
            raise
        time.sleep(0.05)
sock.settimeout(30)
sock.sendall(bytes(n))
sock.close()
"""


def measure_gbit(src_ns: str, dst_ns: str, dst_ip: str) -> float:
    """TCP throughput src -> dst in Gbit/s, moving PAYLOAD bytes."""
    recv = subprocess.Popen(
        ["ip", "netns", "exec", dst_ns, sys.executable, "-c", RECEIVER, dst_ip, str(PORT), str(PAYLOAD)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        assert recv.stdout is not None
        assert recv.stdout.readline().strip() == "ready", recv.stderr.read() if recv.stderr else ""
        subprocess.run(
            ["ip", "netns", "exec", src_ns, sys.executable, "-c", SENDER, dst_ip, str(PORT), str(PAYLOAD)],
            check=True, timeout=30, capture_output=True,
        )
        out, err = recv.communicate(timeout=30)
        assert recv.returncode == 0, err
    finally:
        if recv.poll() is None:
            recv.kill()
            recv.wait()
    got, seconds = out.split()
    return int(got) * 8 / float(seconds) / 1e9


def shaped_gbit(ns: str, dev: str) -> float | None:
    """The rate of the token bucket on the egress of `dev` in `ns`, as tc holds it (Gbit/s; None: none)."""
    out = subprocess.run(["tc", "-j", "-n", ns, "qdisc", "show", "dev", dev], capture_output=True, text=True,
                         check=True).stdout
    tbf = [q for q in json.loads(out) if q.get("kind") == "tbf" and q.get("root")]
    return tbf[0]["options"]["rate"] * 8 / 1e9 if tbf else None


def leftovers(run: str) -> list[str]:
    prefix = run_prefix(run)
    spaces = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=True).stdout.split()
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True, check=True).stdout
    found = [s for s in spaces if s.startswith(prefix)]
    found += [line.split(":")[1].strip() for line in links.splitlines() if prefix in line]
    return found


@pytest.mark.timeout(60)
def test_rates_are_enforced_and_cleanup_is_complete(tmp_path) -> None:
    topo = parse_topology(TOPOLOGY)
    plan = make_plan(topo, str(tmp_path))
    cluster = NetnsCluster(topo, plan)
    nodes = {n.name: n for n in cluster.nodes}
    start = time.monotonic()
    try:
        cluster.create()
        assert set(cluster.names()) >= {n.ns for n in cluster.nodes}
        # each direction of every link shaped at its rate: a node's upload (its NIC) and download
        # (its bridge port), a rack's uplink rack -> spine and spine -> rack
        want = {(n.ns, NODE_IF): NODE_GBIT for n in cluster.nodes}
        want |= {(cluster.fabric, node_port(n.rack_index, n.node_index)): NODE_GBIT for n in cluster.nodes}
        want |= {(cluster.fabric, end): UPLINK_GBIT for ri in range(len(topo.racks)) for end in uplink_ends(ri)}
        assert {link: shaped_gbit(*link) for link in want} == pytest.approx(want)
        within = measure_gbit(nodes["ra0"].ns, nodes["ra1"].ns, nodes["ra1"].ip)
        across = measure_gbit(nodes["ra0"].ns, nodes["rb1"].ns, nodes["rb1"].ip)
        back = measure_gbit(nodes["rb0"].ns, nodes["ra1"].ns, nodes["ra1"].ip)
    finally:
        cluster.destroy()
    print(f"within rack {within:.3f} Gbit/s (limit {NODE_GBIT}); across racks {across:.3f} / {back:.3f} "
          f"Gbit/s (limit {UPLINK_GBIT}); {time.monotonic() - start:.1f} s")
    assert all(math.isfinite(x) for x in (within, across, back))  # a figure for each path (printed above)
    assert leftovers(topo.run) == []
    cluster.destroy()  # idempotent: a second call finds nothing and does not raise

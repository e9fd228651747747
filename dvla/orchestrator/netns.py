"""Emulated clusters (`emulate: netns`): one Linux network namespace per node, rate-limited links.

This module owns everything dvla creates in the kernel's network stack for a run (namespaces per
node and one "fabric" namespace of rack and spine bridges, veths shaped with ``tbf`` at both ends,
a host veth for the orchestrator's control link) and its removal. docs/cluster.md draws the
layout, the names and the rates.
"""

from __future__ import annotations

import ctypes
import hashlib
import ipaddress
import logging
import os
import signal
import socket
import subprocess
import threading
from dataclasses import dataclass
from typing import Iterable

from ..config import Topology
from .process import CommandWrapper, Plan, Process

log = logging.getLogger("dvla.netns")

PREFIX = "dv-"
SUBNET = ipaddress.IPv4Network("10.77.0.0/16")
#: the root namespace's address on the emulated fabric (orchestrator, `dvla status`)
HOST_IP = "10.77.255.254"
#: node n of rack r is 10.77.r.(n + NODE_OFFSET); .1-.9 stay free for future infrastructure
NODE_OFFSET = 10
MAX_RACKS = 255  # rack index 255 would collide with HOST_IP
MAX_NODES_PER_RACK = 254 - NODE_OFFSET
NODE_IF = "eth0"
SPINE = "spine"
HOST_PORT = "host"
CMD_TIMEOUT_S = 30.0
PROBE_TIMEOUT_S = 2.0


class NetnsError(RuntimeError):
    """An `ip`/`tc` command failed, or the emulated cluster is not fully reachable."""


# ----------------------------------------------------------------------------------------------
# Names and addresses


def node_ip(rack_index: int, node_index: int) -> str:
    """Address of node `node_index` of rack `rack_index`: 10.77.<rack>.<node + 10> (a /16)."""
    if not 0 <= rack_index < MAX_RACKS:
        raise ValueError(f"rack index {rack_index} out of range for netns emulation (0..{MAX_RACKS - 1})")
    if not 0 <= node_index < MAX_NODES_PER_RACK:
        raise ValueError(f"node index {node_index} out of range for netns emulation (0..{MAX_NODES_PER_RACK - 1})")
    return f"10.77.{rack_index}.{node_index + NODE_OFFSET}"


def _tag(text: str, n: int) -> str:
    return hashlib.sha1(text.encode()).hexdigest()[:n]


def run_prefix(run: str) -> str:
    """Common prefix of every namespace and host interface of a run: ``dv-<6 hex>-``."""
    return f"{PREFIX}{_tag(run, 6)}-"


def netns_name(run: str, node: str) -> str:
    """Namespace of a node: ``dv-<run tag>-<node tag>``, 15 characters (fits an interface name)."""
    return run_prefix(run) + _tag(node, 5)


def fabric_name(run: str) -> str:
    """Namespace holding the run's rack bridges and spine."""
    return run_prefix(run) + "sw"


def host_link_name(run: str) -> str:
    """Root-namespace end of the veth joining the host to the spine."""
    return run_prefix(run) + "h"


def node_port(rack_index: int, node_index: int) -> str:
    """Rack-bridge end (in the fabric namespace) of a node's veth."""
    return f"p{rack_index}-{node_index}"


def rack_bridge(rack_index: int) -> str:
    return f"br{rack_index}"


def uplink_ends(rack_index: int) -> tuple[str, str]:
    """(rack-bridge end, spine end) of a rack's uplink veth."""
    return f"u{rack_index}r", f"u{rack_index}s"


# ----------------------------------------------------------------------------------------------
# Commands


def _run(cmd: list[str]) -> str:
    """Run an `ip`/`tc`/`sysctl` command; a failure names the command and its stderr."""
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=CMD_TIMEOUT_S)
    except subprocess.CalledProcessError as err:
        stderr = err.stderr.strip() or "(no stderr)"
        raise NetnsError(f"`{' '.join(cmd)}` failed (exit {err.returncode}): {stderr}") from None
    except subprocess.TimeoutExpired:
        raise NetnsError(f"`{' '.join(cmd)}` did not finish in {CMD_TIMEOUT_S:.0f} s") from None
    except FileNotFoundError:
        raise NetnsError(f"`{cmd[0]}` not found: netns emulation needs iproute2 (ip, tc)") from None
    return proc.stdout


def ip(*args: str, ns: str | None = None) -> str:
    """Run ``ip [-n NS] ARGS`` and return its output; a failure raises :class:`NetnsError`."""
    return _run(["ip", *(["-n", ns] if ns else []), *args])


def rate_limit(ns: str | None, dev: str, gbit: float) -> None:
    """Limit the egress of `dev` to `gbit` with a token bucket."""
    rate_bit = int(gbit * 1e9)
    # the bucket must hold a whole GSO super-packet: tbf cuts a larger one into MTU-sized packets
    # in software, multiplying the receiver's per-byte cost (real NICs segment in hardware); above
    # that, a few ms of line rate keeps the shaper accurate at high rates
    burst = max(256 * 1024, rate_bit // 8 // 500)
    _run(["tc", *(["-n", ns] if ns else []), "qdisc", "replace", "dev", dev, "root", "tbf",
          "rate", f"{rate_bit}bit", "burst", str(burst), "latency", "25ms"])


def _no_ipv6(ns: str | None, dev: str = "all") -> None:
    """IPv6 off: nothing here uses it, and it would add router/neighbour solicitation chatter."""
    keys = [f"net.ipv6.conf.{dev}.disable_ipv6=1"] + (["net.ipv6.conf.default.disable_ipv6=1"] if dev == "all" else [])
    prefix = ["ip", "netns", "exec", ns] if ns else []
    try:
        _run([*prefix, "sysctl", "-qw", *keys])
    except NetnsError as err:  # a kernel without IPv6 has nothing to turn off
        log.debug("ipv6 left as is: %s", err)


def list_netns() -> list[str]:
    """Names of every named network namespace (``ip netns list``)."""
    return [line.split()[0] for line in ip("netns", "list").splitlines() if line.strip()]


def list_links(ns: str | None = None) -> list[str]:
    """Interface names in a namespace (root when None), without the ``@peer`` suffix."""
    names = []
    for line in ip("-o", "link", "show", ns=ns).splitlines():
        parts = line.split(":", 2)
        if len(parts) >= 2:
            names.append(parts[1].strip().split("@")[0])
    return names


# ----------------------------------------------------------------------------------------------
# Removal


def _kill_netns_pids(ns: str) -> list[int]:
    """SIGKILL whatever still runs in one of our namespaces (it keeps the namespace alive)."""
    try:
        pids = [int(p) for p in ip("netns", "pids", ns).split()]
    except NetnsError:
        return []
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return pids


def _remove(names: Iterable[str]) -> list[str]:
    """Remove the named namespaces / root-namespace links that exist; never raises."""
    removed: list[str] = []
    try:
        spaces, links = set(list_netns()), set(list_links())
    except NetnsError as err:
        log.error("cannot list namespaces or links: %s", err)
        return removed
    # Host links first: removing them is synchronous (a namespace's links die asynchronously).
    ordered = sorted(set(names), key=lambda n: (n not in links, n))
    for name in ordered:
        try:
            if name in links:
                ip("link", "del", name)
            elif name in spaces:
                pids = _kill_netns_pids(name)
                if pids:
                    log.warning("killed %d leftover process(es) in %s: %s", len(pids), name, pids)
                ip("netns", "del", name)
            else:
                continue
        except NetnsError as err:
            log.error("could not remove %s: %s", name, err)
            continue
        log.info("removed %s", name)
        removed.append(name)
    return removed


def destroy_names(run: str, names: Iterable[str]) -> list[str]:
    """Remove a run's leftovers: the given names plus anything carrying the run's prefix."""
    prefix = run_prefix(run)
    wanted = set(names)
    try:
        wanted |= {n for n in list_netns() if n.startswith(prefix)}
        wanted |= {n for n in list_links() if n.startswith(prefix)}
    except NetnsError as err:
        log.error("cannot list namespaces or links: %s", err)
    return _remove(wanted)


# ----------------------------------------------------------------------------------------------
# Reachability probe: sockets opened inside each namespace from one helper thread (setns is
# per thread), so checking every link costs no process start.

_CLONE_NEWNET = 0x40000000


def _setns(fd: int) -> None:
    """Move the calling thread into the network namespace open at `fd`."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, _CLONE_NEWNET) != 0:
        code = ctypes.get_errno()
        raise OSError(code, f"setns: {os.strerror(code)}")


def enter_netns(name: str) -> None:
    """Move the calling thread into the named namespace (``ip netns add NAME``); a process that
    calls this before it starts threads or opens sockets runs inside that namespace."""
    fd = os.open(f"/run/netns/{name}", os.O_RDONLY)
    try:
        _setns(fd)
    finally:
        os.close(fd)


@dataclass(frozen=True)
class _Node:
    name: str
    rack: str
    rack_index: int
    node_index: int
    ns: str
    ip: str


def _probe_connects(nodes: list[_Node], pairs: list[tuple[str, str]]) -> dict[tuple[str, str], str | None]:
    """TCP-connect for each (src, dst) pair ("host" is the root namespace); error text or None."""
    by_name = {n.name: n for n in nodes}
    results: dict[tuple[str, str], str | None] = {}
    failure: list[BaseException] = []

    def work() -> None:
        home = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
        listeners: dict[str, socket.socket] = {}
        try:
            for dst in sorted({d for _s, d in pairs}):
                enter_netns(by_name[dst].ns)
                sock = socket.socket()
                sock.bind((by_name[dst].ip, 0))
                sock.listen(64)
                listeners[dst] = sock
            for src, dst in pairs:
                if src == "host":
                    _setns(home)
                else:
                    enter_netns(by_name[src].ns)
                results[(src, dst)] = _connect(by_name[dst].ip, listeners[dst].getsockname()[1])
        except BaseException as err:  # re-raised by the caller, in its own thread
            failure.append(err)
        finally:
            for sock in listeners.values():
                sock.close()
            os.close(home)

    # A helper thread, so the caller's own namespace is never touched.
    thread = threading.Thread(target=work, name="netns-probe", daemon=True)
    thread.start()
    thread.join()
    if failure:
        raise NetnsError(f"reachability probe failed: {failure[0]}")
    return results


def _connect(ip: str, port: int) -> str | None:
    try:
        with socket.create_connection((ip, port), timeout=PROBE_TIMEOUT_S):
            return None
    except socket.timeout:
        return "timed out"
    except OSError as err:
        return os.strerror(err.errno) if err.errno else str(err)


# ----------------------------------------------------------------------------------------------
# The cluster


class NetnsWrapper(CommandWrapper):
    """Runs a role inside its node's namespace."""

    def __call__(self, proc: Process, argv: list[str]) -> list[str]:
        if proc.netns is None:
            raise NetnsError(f"{proc.config.name} has no network namespace in a netns run")
        return ["ip", "netns", "exec", proc.netns, *argv]

    def fork_into(self, proc: Process) -> str | None:
        return proc.netns


class NetnsCluster:
    """The namespaces, bridges and links of one emulated run."""

    def __init__(self, topo: Topology, plan: Plan) -> None:
        self.topo = topo
        self.run = topo.run
        self.fabric = fabric_name(topo.run)
        self.host_link = host_link_name(topo.run)
        self.nodes = self._nodes(topo, plan)
        self._created: list[str] = []

    @staticmethod
    def _nodes(topo: Topology, plan: Plan) -> list[_Node]:
        nodes, seen = [], {}
        for ri, rack in enumerate(topo.racks):
            for ni, node in enumerate(rack.nodes):
                ip = plan.addresses[node.name]
                if ipaddress.IPv4Address(ip) not in SUBNET or ip == HOST_IP:
                    raise NetnsError(f"node {node.name}: address {ip} is outside the emulated fabric {SUBNET}")
                ns = netns_name(topo.run, node.name)
                if ns in seen:  # 20-bit node tags: vanishingly rare, but would merge two nodes
                    raise NetnsError(f"nodes {seen[ns]} and {node.name} map to the same namespace {ns}: rename one")
                seen[ns] = node.name
                nodes.append(_Node(node.name, rack.name, ri, ni, ns, ip))
        return nodes

    # -- public API ----------------------------------------------------------------------------

    def names(self) -> list[str]:
        """Every namespace and root-namespace interface created so far (for `dvla down`)."""
        return list(self._created)

    def create(self) -> None:
        """Build the whole fabric and check it; on any failure remove what was built and raise."""
        if os.geteuid() != 0:
            raise NetnsError("emulate: netns needs root (network namespaces, veths and tc)")
        if self.topo.shared_memory:
            log.warning("shared_memory is on: local processes will bypass the emulated links")
        stale = destroy_names(self.run, [])
        if stale:
            log.warning("removed leftovers of an earlier %s run: %s", self.run, ", ".join(stale))
        self._check_host_routes()
        try:
            self._build_fabric()
            for node in self.nodes:
                self._build_node(node)
            self._build_host_link()
            self.verify()
        except BaseException:
            self.destroy()
            raise
        log.info("netns cluster %s up: %d nodes, fabric %s", self.run, len(self.nodes), self.fabric)

    def destroy(self) -> list[str]:
        """Remove everything of this run (also leftovers by prefix); idempotent, never raises."""
        removed = destroy_names(self.run, [self.host_link, self.fabric, *(n.ns for n in self.nodes)])
        self._created.clear()
        return removed

    def verify(self) -> None:
        """Connect host -> every node and node i -> node i+1 (a ring crossing every uplink)."""
        pairs = [("host", n.name) for n in self.nodes]
        if len(self.nodes) > 1:
            pairs += [(a.name, b.name) for a, b in zip(self.nodes, self.nodes[1:] + self.nodes[:1])]
        results = _probe_connects(self.nodes, pairs)
        failed = {p: e for p, e in results.items() if e is not None}
        if failed:
            raise NetnsError(self._describe_failures(results, failed))

    # -- building ------------------------------------------------------------------------------

    def _check_host_routes(self) -> None:
        """The host link adds a connected 10.77.0.0/16 route: refuse if the host already routes it."""
        routes = ip("-4", "route", "show", "root", str(SUBNET)) + ip("-4", "route", "show", "match", str(SUBNET))
        clashes = [r for r in routes.splitlines() if r.strip() and not r.startswith("default")]
        if clashes:
            raise NetnsError(
                f"the host already routes part of {SUBNET} ({clashes[0].strip()}): another netns run is up"
                " (`dvla down` it) or the host network uses this range"
            )

    def _add_netns(self, ns: str) -> None:
        ip("netns", "add", ns)
        self._created.append(ns)
        _no_ipv6(ns)
        ip("link", "set", "lo", "up", ns=ns)

    def _add_bridge(self, name: str) -> None:
        ip("link", "add", name, "type", "bridge", "stp_state", "0", "forward_delay", "0", ns=self.fabric)
        ip("link", "set", name, "up", ns=self.fabric)

    def _build_fabric(self) -> None:
        self._add_netns(self.fabric)
        self._add_bridge(SPINE)
        for ri in range(len(self.topo.racks)):
            self._add_bridge(rack_bridge(ri))
            rack_end, spine_end = uplink_ends(ri)
            ip("link", "add", rack_end, "type", "veth", "peer", "name", spine_end, ns=self.fabric)
            ip("link", "set", rack_end, "master", rack_bridge(ri), "up", ns=self.fabric)
            ip("link", "set", spine_end, "master", SPINE, "up", ns=self.fabric)
            # egress of the rack end = rack -> spine; egress of the spine end = spine -> rack
            rate_limit(self.fabric, rack_end, self.topo.links.rack_uplink_gbit)
            rate_limit(self.fabric, spine_end, self.topo.links.rack_uplink_gbit)

    def _build_node(self, node: _Node) -> None:
        self._add_netns(node.ns)
        port = node_port(node.rack_index, node.node_index)
        ip("link", "add", port, "type", "veth", "peer", "name", NODE_IF, "netns", node.ns, ns=self.fabric)
        ip("link", "set", port, "master", rack_bridge(node.rack_index), "up", ns=self.fabric)
        ip("addr", "add", f"{node.ip}/{SUBNET.prefixlen}", "dev", NODE_IF, ns=node.ns)
        ip("link", "set", NODE_IF, "up", ns=node.ns)
        # egress of eth0 = node upload; egress of the bridge port = node download
        rate_limit(node.ns, NODE_IF, self.topo.links.node_gbit)
        rate_limit(self.fabric, port, self.topo.links.node_gbit)

    def _build_host_link(self) -> None:
        ip("link", "add", self.host_link, "type", "veth", "peer", "name", HOST_PORT, "netns", self.fabric)
        self._created.append(self.host_link)
        _no_ipv6(None, self.host_link)
        ip("link", "set", HOST_PORT, "master", SPINE, "up", ns=self.fabric)
        ip("addr", "add", f"{HOST_IP}/{SUBNET.prefixlen}", "dev", self.host_link)
        ip("link", "set", self.host_link, "up")

    # -- diagnosis -----------------------------------------------------------------------------

    def _path(self, src: str, dst: str) -> list[str]:
        """Links a packet from src to dst crosses, by name."""
        by_name = {n.name: n for n in self.nodes}
        d = by_name[dst]
        if src == "host":
            hops = [f"host link {self.host_link}"]
        else:
            s = by_name[src]
            hops = [f"{s.name} NIC {node_port(s.rack_index, s.node_index)}"]
            if s.rack_index == d.rack_index:
                return hops + [f"{d.name} NIC {node_port(d.rack_index, d.node_index)}"]
            hops.append(f"rack {s.rack} uplink {uplink_ends(s.rack_index)[0]}")
        hops.append(f"rack {d.rack} uplink {uplink_ends(d.rack_index)[0]}")
        hops.append(f"{d.name} NIC {node_port(d.rack_index, d.node_index)}")
        return hops

    def _describe_failures(self, results: dict[tuple[str, str], str | None], failed: dict[tuple[str, str], str]) -> str:
        """Every failed check with its path, and the links on all failed paths but no good one."""
        ips = {n.name: n.ip for n in self.nodes} | {"host": HOST_IP}
        good = {hop for p, e in results.items() if e is None for hop in self._path(*p)}
        suspects = set.intersection(*(set(self._path(*p)) for p in failed)) - good
        lines = [f"emulated cluster {self.run}: {len(failed)} of {len(results)} reachability checks failed"]
        if suspects:
            lines.append(f"failing link: {', '.join(sorted(suspects))} (bridge ports live in namespace {self.fabric})")
        for (src, dst), err in failed.items():
            path = " -> ".join(self._path(src, dst))
            lines.append(f"  {src} ({ips[src]}) -> {dst} ({ips[dst]}): {err}; path: {path}")
        return "\n".join(lines)

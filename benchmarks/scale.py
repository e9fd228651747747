"""`dvla bench scale`: the broadcast model (:mod:`dvla.orchestrator.simulate`) against measured
weight transfers on emulated clusters of growing size.

1. **Calibration.** A tiny emulated cluster (one rack: source, relay and by default one sink, a
   node each, on 10 Gbit/s links so the links are not the limit) moves ``calibration_versions``
   versions of the same size as the runs; the median CPU seconds each process spent per MiB of a
   version (from ``/proc``, :func:`benchmarks.replication.measure`) give the model's
   :class:`HostCosts`, with every process sharing this machine's ``os.cpu_count()`` cores. More
   sinks or slower links (``calibration_sinks``, ``calibration_gbit``) calibrate closer to the
   runs' relays, which feed several children at the topology's link rates.
2. **Runs.** For each topology (``topologies/{N}node.yaml``), the topology's own tree of real
   :mod:`benchmarks.repnode` processes (evaluator removed, ``full`` encoding, shared memory off,
   the file's link rates) moves one warm-up version, then ``versions`` measured ones; each row has
   the measured ``all_held_s`` (median, min, max), the model's ``tree_s`` with the calibrated CPU
   costs and without any (links and pipelining alone), the S/B bound, and
   ``predicted / measured``. Beside them, so a prediction that misses shows where the time went:
   the bytes every link direction carried per version (interface counters of the namespaces) as
   copies of a version against the model's copies (one per tree edge crossing it), the busiest
   link and how long its measured bytes take at its rate; the CPU per MiB of every process kind
   in the run (also net of its background CPU: idle lanes, keep-alives, status polls, measured
   for a few seconds before the first version) against the calibration's; the whole machine's
   CPU per version; and the per-version timings of :func:`benchmarks.replication.measure`.

Every cluster's namespaces are removed when it closes (also on errors); the document records
that none of this bench's namespaces is left.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import statistics
import subprocess
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable

from dvla.config import NodeConfig, RackConfig, RolePlacement, Topology
from dvla.orchestrator.netns import list_netns, node_port, run_prefix, uplink_ends
from dvla.orchestrator.simulate import HostCosts, link_rate, path_links, simulate_broadcast
from dvla.orchestrator.topology import load_topology
from .repcluster import MODE_OF_KIND, RepCluster
from .replication import MIB, measure, transfer_topology

#: run names (so namespace prefixes) of the calibration cluster and of the N-node runs
CAL_RUN = "scalecal"
#: calibration links: fast enough that the CPU, not the link, paces a version
CAL_GBIT = 10.0
#: seconds of the background window before a run's versions (status polls, no version moving)
BACKGROUND_S = 3.0
#: the driver polls the sinks' status this often while a version moves (as `measure` does)
POLL_S = 0.5


def run_name(nodes: int) -> str:
    return f"scale{nodes}"


def _tx_bytes(ns: str) -> dict[str, int]:
    """Bytes each interface of namespace `ns` has sent (``ip -s -j link``)."""
    out = subprocess.run(["ip", "-n", ns, "-s", "-j", "link", "show"], capture_output=True, text=True,
                         check=True, timeout=10).stdout
    return {link["ifname"]: int(link["stats64"]["tx"]["bytes"]) for link in json.loads(out)}


def link_bytes(cluster: RepCluster) -> dict[str, int]:
    """Bytes sent so far on every link direction of the emulated cluster, named as the model names
    them: a node's ``eth0`` egress is its NIC out, its rack-bridge port's egress its NIC in, a rack
    uplink's rack end its uplink out, the spine end its uplink in."""
    net = cluster.netns
    if net is None:
        return {}
    fabric = _tx_bytes(net.fabric)
    out = {}
    for ri, rack in enumerate(cluster.topo.racks):
        rack_end, spine_end = uplink_ends(ri)
        out[f"{rack.name} uplink out"], out[f"{rack.name} uplink in"] = fabric[rack_end], fabric[spine_end]
    for n in net.nodes:
        out[f"{n.name} NIC in"] = fabric[node_port(n.rack_index, n.node_index)]
        out[f"{n.name} NIC out"] = _tx_bytes(n.ns)["eth0"]
    return out


def model_copies(cluster: RepCluster) -> dict[str, int]:
    """Copies of a version the model puts on each link direction: one per tree edge it carries."""
    where = {p.config.name: (p.config.rack, p.config.node) for p in cluster.plan.processes}
    copies: dict[str, int] = defaultdict(int)
    for p in cluster.plan.processes:
        if p.config.parent:
            for link in path_links(where, p.config.parent, p.config.name):
                copies[link] += 1
    return dict(copies)


def link_figures(cluster: RepCluster, moved: dict[str, int], versions: int, size_bytes: int) -> dict[str, Any]:
    """Measured copies per version on every link direction beside the model's, the busiest link
    of each, and how long the busiest measured link needs for its bytes at its rate."""
    model = model_copies(cluster)
    copies = {k: b / (versions * size_bytes) for k, b in moved.items()}
    links = {k: {"copies": round(copies.get(k, 0.0), 3), "model_copies": model.get(k, 0)}
             for k in sorted(set(copies) | set(model)) if copies.get(k, 0.0) >= 0.05 or model.get(k)}
    if not copies:
        return {"links": links}
    busiest = max(copies, key=lambda k: copies[k] * size_bytes / link_rate(cluster.topo, k))
    model_busiest = max(model, key=lambda k: model[k] * size_bytes / link_rate(cluster.topo, k)) if model else None
    return {
        "links": links,
        "busiest_link": busiest,
        "busiest_link_copies": copies[busiest],
        # the measured bytes of the busiest link at its rate (framing as the model counts it)
        "busiest_link_s": copies[busiest] * size_bytes / link_rate(cluster.topo, busiest),
        "model_busiest_link": model_busiest,
        "model_busiest_link_copies": model.get(model_busiest, 0) if model_busiest else 0,
    }


def host_busy_s() -> float:
    """CPU seconds this machine has been busy so far, all cores (``/proc/stat``: all but idle, iowait)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return (sum(fields[:8]) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")


def background_cpu(cluster: RepCluster, seconds: float) -> dict[str, float]:
    """CPU seconds per second each process spends with no version moving while the driver polls
    the sinks' status as `measure` does (liveliness, keep-alives, idle lanes, status replies)."""
    cpu0, t0 = cluster.cpu_by_process(), time.monotonic()
    while time.monotonic() - t0 < seconds:
        for n in cluster.sinks:
            cluster.status(n, timeout=1.0)
        time.sleep(POLL_S)
    cpu1, dt = cluster.cpu_by_process(), time.monotonic() - t0
    return {n: (cpu1[n] - cpu0[n]) / dt for n in cpu1 if n in cpu0}


def cluster_rss_mib(cluster: RepCluster) -> float:
    """Resident memory of the cluster's processes, MiB (``VmRSS``)."""
    total = 0
    for pid in cluster.launcher.pids().values():
        try:
            status = Path(f"/proc/{pid}/status").read_text()
        except OSError:
            continue
        total += next((int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:")), 0)
    return total / 1024


def calibration_topology(base: Topology, sinks: int = 1, gbit: float = CAL_GBIT) -> Topology:
    """One rack: source (actor) -> relay (replicator) -> `sinks` sinks (rollouts), a node each."""
    roles = ("actor", "replicator") + ("rollout",) * sinks
    nodes = tuple(NodeConfig(name=f"cal{i}", roles=(RolePlacement(role=role),)) for i, role in enumerate(roles))
    topo = dataclasses.replace(base, racks=(RackConfig(name="cal", nodes=nodes),))
    return transfer_topology(topo, gbit, gbit, run=CAL_RUN)


def cpu_per_mib_by_kind(cluster: RepCluster, run: dict[str, Any], size_mib: float,
                        background: dict[str, float] | None = None) -> dict[str, Any]:
    """Median over the measured versions of each process's CPU seconds per MiB, then per kind the
    median (and max) over its processes, each relay's own figure beside its number of children;
    with `background` (CPU s/s with no version moving) also the same net of it (``*_net``)."""
    kind_of = {p.config.name: MODE_OF_KIND[p.config.kind] for p in cluster.plan.processes}
    counted = [v for v in run["versions"] if not v["warmup"]]
    bg = background or {}

    def per_proc(net: bool) -> dict[str, float]:
        return {n: statistics.median(v["cpu_s_by_process"].get(n, 0.0) - (bg.get(n, 0.0) * v["all_held_s"] if net else 0.0)
                                     for v in counted) / size_mib for n in kind_of}

    gross, net = per_proc(False), per_proc(True)
    out: dict[str, Any] = {}
    for kind in ("source", "relay", "sink"):
        for suffix, figures in (("", gross), ("_net", net)):
            vals = [x for n, x in figures.items() if kind_of[n] == kind]
            out[kind + suffix] = statistics.median(vals) if vals else None
            out[f"{kind}{suffix}_max"] = max(vals) if vals else None
        out[f"{kind}_background_s_per_s"] = statistics.median(bg[n] for n in bg if kind_of[n] == kind) if bg else None
    out["relays"] = {n: {"s_per_mib": gross[n], "s_per_mib_net": net[n], "children": len(cluster.children_of(n))}
                     for n in cluster.relays}
    return out


def calibrate(base: Topology, numel: int, versions: int, tmp: Path, progress: Callable[[str], None], *,
              sinks: int = 1, gbit: float = CAL_GBIT) -> dict[str, Any]:
    """CPU seconds per MiB of source, relay and sink, measured on a one-rack cluster."""
    size_mib = numel * 4 / MIB
    cluster = RepCluster(calibration_topology(base, sinks, gbit), tmp / CAL_RUN, numel)
    progress(f"calibration: {len(cluster.plan.processes)} processes, {size_mib:.0f} MiB versions, {gbit:g} Gbit/s links")
    cluster.start()
    try:
        background = background_cpu(cluster, BACKGROUND_S)
        run = measure(cluster, versions, timeout_s=120.0, progress=lambda m: progress("calibration " + m),
                      counters=lambda: link_bytes(cluster))
        cpu = cpu_per_mib_by_kind(cluster, run, size_mib, background)
        links = link_figures(cluster, run["counter_bytes"], versions, numel * 4)
    finally:
        cluster.close()
    return {
        "topology": f"1 rack, {sinks + 2} nodes: actor -> replicator -> {sinks} rollout(s)",
        "sinks": sinks,
        "link_gbit": gbit,
        "size_mib": size_mib,
        "versions": versions,
        "source_s_per_mib": cpu["source"],
        "relay_s_per_mib": cpu["relay"],
        "sink_s_per_mib": cpu["sink"],
        "shared_cores": os.cpu_count(),
        "cpu_s_per_mib": cpu,
        "links": links["links"],
        "all_held_s_median": run["median_s"],
        "run": run,
    }


def costs_of(cal: dict[str, Any]) -> HostCosts:
    return HostCosts(source_s_per_mib=cal["source_s_per_mib"], relay_s_per_mib=cal["relay_s_per_mib"],
                     sink_s_per_mib=cal["sink_s_per_mib"], shared_cores=cal["shared_cores"])


def where_time_goes(run: dict[str, Any]) -> dict[str, Any]:
    """Medians over the measured versions of the source's last put, the relays' last chunk in and
    out, the sinks' last chunk and their verify-and-swap (each the latest over its processes)."""
    counted = [v for v in run["versions"] if not v["warmup"]]

    def med(get: Callable[[dict[str, Any]], list[float]]) -> float | None:
        vals = [max(xs) for xs in (get(v) for v in counted) if xs]
        return statistics.median(vals) if vals else None

    return {
        "send_s": statistics.median(v["send_s"] for v in counted),
        "relay_last_in_s": med(lambda v: [r["last_in_s"] for r in v["relays"].values()]),
        "relay_last_out_s": med(lambda v: [r["last_out_s"] for r in v["relays"].values()]),
        "relay_lag_ms": med(lambda v: [r["lag_ms"] for r in v["relays"].values()]),
        "sink_last_chunk_s": med(lambda v: list(v["last_chunk_s"].values())),
        "sink_apply_s": med(lambda v: list(v["apply_s"].values())),
        "cluster_cpu_s": run["cluster_cpu_s_median"],
    }


def run_one(topology: Path, numel: int, versions: int, costs: HostCosts, tmp: Path,
            progress: Callable[[str], None]) -> dict[str, Any]:
    """One topology's tree: measured against predicted with and without CPU costs."""
    base = load_topology(topology)
    nodes = sum(len(r.nodes) for r in base.racks)
    topo = transfer_topology(base, base.links.node_gbit, base.links.rack_uplink_gbit, run=run_name(nodes))
    size_bytes = numel * 4
    cluster = RepCluster(topo, tmp / topo.run, numel)  # drops the evaluator
    pred = simulate_broadcast(cluster.topo, cluster.plan, size_bytes, costs)
    bare = simulate_broadcast(cluster.topo, cluster.plan, size_bytes,
                              HostCosts(shared_cores=costs.shared_cores))
    timeout_s = max(120.0, 20 * pred.tree_s)
    progress(f"{nodes} nodes: starting {len(cluster.plan.processes)} processes; predicted {pred.tree_s:.2f} s "
             f"({bare.tree_s:.2f} s without CPU)")
    t0 = time.monotonic()
    cluster.start(timeout_s=120.0)
    started_s = time.monotonic() - t0
    busy: list[float] = []

    def counters() -> dict[str, int]:
        busy.append(host_busy_s())
        return link_bytes(cluster)

    try:
        background = background_cpu(cluster, BACKGROUND_S)
        run = measure(cluster, versions, timeout_s, lambda m: progress(f"{nodes} nodes {m}"), counters)
        rss_mib = cluster_rss_mib(cluster)
        cpu = cpu_per_mib_by_kind(cluster, run, size_bytes / MIB, background)
        links = link_figures(cluster, run["counter_bytes"], versions, size_bytes)
        children = {n: cluster.children_of(n) for n in [cluster.source, *cluster.relays]}
    finally:
        cluster.close()
    processes_cpu = sum(sum(v["cpu_s_by_process"].values()) for v in run["versions"] if not v["warmup"])
    measured = run["median_s"]
    return {
        "topology": str(topology),
        "nodes": nodes,
        "racks": len(base.racks),
        "processes": len(cluster.plan.processes),
        "sinks": len(cluster.sinks),
        "relays": len(cluster.relays),
        "node_gbit": topo.links.node_gbit,
        "rack_uplink_gbit": topo.links.rack_uplink_gbit,
        "relay_fanout": topo.replication.relay_fanout,
        "size_bytes": size_bytes,
        "bound_s": pred.bound_s,
        "bound_link": pred.bound_link,
        "measured_s": measured,
        "measured_min_s": run["min_s"],
        "measured_max_s": run["max_s"],
        "predicted_s": pred.tree_s,
        "predicted_no_cpu_s": bare.tree_s,
        "predicted_over_measured": pred.tree_s / measured,
        "predicted_no_cpu_over_measured": bare.tree_s / measured,
        "measured_over_bound": measured / pred.bound_s,
        "tree_bottleneck": pred.tree_bottleneck,
        "tree_bottleneck_copies": pred.tree_bottleneck_copies,
        "depth": pred.depth,
        "predicted_per_leaf_s": pred.per_leaf_s,
        "cpu_s_per_mib": cpu,
        # this machine's CPU over the measured versions (all processes and the kernel) beside
        # the cluster processes' own, per version
        "host_cpu_busy_s_per_version": (busy[-1] - busy[0]) / versions if len(busy) == 2 else None,
        "cluster_cpu_s_per_version": processes_cpu / versions,
        "cluster_rss_mib": rss_mib,
        **links,
        "where_time_goes": where_time_goes(run),
        "tree_children": children,
        "start_s": started_s,
        "run_s": time.monotonic() - t0,
        "tree": run,
    }


def leftover_namespaces(runs: list[str]) -> list[str]:
    """This bench's namespaces that still exist (should be none)."""
    prefixes = tuple(run_prefix(r) for r in runs)
    return [n for n in list_netns() if n.startswith(prefixes)]


def run_bench(
    topologies: list[Path],
    *,
    size_mib: float = 64.0,
    versions: int = 3,
    calibration_versions: int = 5,
    calibration_sinks: int = 1,
    calibration_gbit: float = CAL_GBIT,
    progress: Callable[[str], None] = lambda m: None,
) -> dict[str, Any]:
    """Calibrate, then measure and predict every topology's broadcast (needs root for netns)."""
    numel = int(size_mib * MIB) // 4
    bases = [load_topology(t) for t in topologies]
    load_before = os.getloadavg()
    doc: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
                    "loadavg_before": load_before},
        "size_bytes": numel * 4,
        "versions": versions,
    }
    runs = [CAL_RUN] + [run_name(sum(len(r.nodes) for r in b.racks)) for b in bases]
    rows = []
    try:
        with tempfile.TemporaryDirectory(prefix="dvla-bench-scale-") as tmp:
            t0 = time.monotonic()
            cal = calibrate(bases[0], numel, calibration_versions, Path(tmp), progress,
                            sinks=calibration_sinks, gbit=calibration_gbit)
            cal["run_s"] = time.monotonic() - t0
            doc["calibration"] = cal
            costs = costs_of(cal)
            progress(f"calibration: source {cal['source_s_per_mib'] * 1e3:.2f}, relay {cal['relay_s_per_mib'] * 1e3:.2f}, "
                     f"sink {cal['sink_s_per_mib'] * 1e3:.2f} ms CPU per MiB")
            for path in topologies:
                rows.append(run_one(path, numel, versions, costs, Path(tmp), progress))
    finally:
        doc["rows"] = rows
        doc["netns_left"] = leftover_namespaces(runs)
    doc["machine"]["loadavg_after"] = os.getloadavg()
    if doc["netns_left"]:
        raise RuntimeError(f"namespaces left behind: {', '.join(doc['netns_left'])}")
    return doc


def format_table(doc: dict[str, Any]) -> str:
    cal = doc["calibration"]
    lines = [
        f"calibration ({cal['topology']}, {cal['size_mib']:.0f} MiB, median of {cal['versions']} versions): CPU ms per MiB "
        f"source {cal['source_s_per_mib'] * 1e3:.2f}, relay {cal['relay_s_per_mib'] * 1e3:.2f}, "
        f"sink {cal['sink_s_per_mib'] * 1e3:.2f}; {cal['shared_cores']} shared cores",
        f"{'nodes':>5} {'procs':>5} {'MiB':>4} {'bound_s':>7} {'measured_s (min-max)':>22} {'pred_s':>7} "
        f"{'no_cpu_s':>8} {'pred/meas':>9} {'no_cpu/meas':>11}  busiest link: measured copies (model)",
    ]
    for r in doc["rows"]:
        meas = f"{r['measured_s']:.2f} ({r['measured_min_s']:.2f}-{r['measured_max_s']:.2f})"
        busiest = "-"
        if r.get("busiest_link"):
            model = r["links"].get(r["busiest_link"], {}).get("model_copies", 0)
            busiest = (f"{r['busiest_link']}: {r['busiest_link_copies']:.2f} ({model}), {r['busiest_link_s']:.2f} s at its rate; "
                       f"model's busiest {r['model_busiest_link']}: {r['model_busiest_link_copies']}")
        lines.append(
            f"{r['nodes']:>5} {r['processes']:>5} {r['size_bytes'] / MIB:>4.0f} {r['bound_s']:>7.2f} {meas:>22} "
            f"{r['predicted_s']:>7.2f} {r['predicted_no_cpu_s']:>8.2f} {r['predicted_over_measured']:>9.2f} "
            f"{r['predicted_no_cpu_over_measured']:>11.2f}  {busiest}")
    lines.append("CPU ms per MiB in the runs, source / relay / sink (net of background):")
    for r in doc["rows"]:
        c = r["cpu_s_per_mib"]
        lines.append(f"{r['nodes']:>5} nodes: {c['source'] * 1e3:.2f} / {c['relay'] * 1e3:.2f} / {c['sink'] * 1e3:.2f}"
                     f"  ({c['source_net'] * 1e3:.2f} / {c['relay_net'] * 1e3:.2f} / {c['sink_net'] * 1e3:.2f});"
                     f"  cluster {r['cluster_cpu_s_per_version']:.1f} s, host {r['host_cpu_busy_s_per_version']:.1f} s CPU per version")
    return "\n".join(lines)

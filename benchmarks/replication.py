"""`dvla bench replication`: the weight tree against a star broadcast and the link bound, on an
emulated cluster, plus the bytes each encoding puts on the wire in real training.

Part 1, transfer (every figure from the same cluster, in the same run):

- ``tree``: the topology's own tree (actor -> rack replicators -> rollouts), real
  :mod:`benchmarks.repnode` processes in network namespaces with rate-limited links. For each of
  ``versions`` full versions of ``size_mib`` MiB: time from the source starting to encode until
  the last rollout holds it, verified (checksum) and swappable. The first version is a warm-up
  (connections, TCP slow start) and is reported but not counted.
- ``star``: the same nodes and links without replicators: the actor sends every rollout its copy.
- ``bound_s`` = S / (slowest link rate on any path): no scheme delivers faster.
- ``actor_uplink_bytes_over_s``: bytes the actor's node NIC sent during the measured versions,
  per version, divided by S (how many copies left the actor's node).

Part 2, encodings in training (optional, ``training_steps > 0``): `dvla up` of a local topology
once per encoding with the same seed and step budget; bytes published per version relative to
``full`` and the final eval success of each run beside it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from dvla.config import LinkConfig, Topology
from dvla.orchestrator.simulate import simulate_broadcast
from benchmarks.ports import free_port_block
from dvla.orchestrator.topology import dump_topology_yaml, load_topology
from .repcluster import RepCluster, without_roles

MIB = 1 << 20


def transfer_topology(topo: Topology, node_gbit: float, uplink_gbit: float, run: str) -> Topology:
    """`topo` set up for the transfer measurement: full encoding, the given link rates, no SHM."""
    rep = dataclasses.replace(topo.replication, encoding="full")
    return dataclasses.replace(
        topo, run=run, replication=rep, shared_memory=False,
        links=LinkConfig(node_gbit=node_gbit, rack_uplink_gbit=uplink_gbit),
    )


def slowest_link_gbit(topo: Topology) -> float:
    """Slowest link any version must cross: the rack uplink when there are several racks."""
    rates = [topo.links.node_gbit] + ([topo.links.rack_uplink_gbit] if len(topo.racks) > 1 else [])
    return min(rates)


def measure(cluster: RepCluster, versions: int, timeout_s: float, progress: Callable[[str], None],
            counters: Callable[[], dict[str, int]] | None = None) -> dict[str, Any]:
    """Publish `versions` + 1 versions one after the other; per-version delivery times.

    `counters`, when given, reads cumulative byte counters (e.g. every link of the emulated
    cluster); the result's ``counter_bytes`` is what they moved during the measured versions."""
    per_version = []
    tx0 = None
    c0: dict[str, int] = {}
    for v in range(1, versions + 2):
        if v == 2:  # the warm-up version is done: count the actor node's bytes from here
            tx0 = cluster.node_tx_bytes(cluster.source)
            c0 = counters() if counters is not None else {}
        cpu0 = cluster.cpu_by_process()
        cluster.publish(v)
        # Sinks stamp the moment they hold a version themselves (held_ns), so polling slowly does
        # not change the figure; polling at 10 Hz cost the cluster ~8 status round trips per
        # 100 ms (signing, routing, replies) on the same two cores the transfer needs.
        held = cluster.wait_held(v, timeout_s=timeout_s, poll_s=0.5)
        cpu1 = cluster.cpu_by_process()
        cpu_by = {n: round(cpu1[n] - cpu0[n], 5) for n in cpu1 if n in cpu0}
        cpu_s = sum(cpu_by.values())
        pub = _wait_sent(cluster, v, timeout_s)
        relays = relay_timing(cluster, v, pub["t0_ns"], held)
        times = {n: (h["held"][str(v)]["held_ns"] - pub["t0_ns"]) / 1e9 for n, h in held.items()}
        bad = sorted(n for n, h in held.items() if h["held"][str(v)]["checksum"] != pub["checksum"])
        if bad:
            raise RuntimeError(f"v{v}: replicas differ from the published version: {', '.join(bad)}")
        per_version.append({
            "version": v,
            "warmup": v == 1,
            "all_held_s": max(times.values()),
            "first_held_s": min(times.values()),
            "encode_s": (pub["encoded_ns"] - pub["t0_ns"]) / 1e9,
            "send_s": (pub["sent_ns"] - pub["t0_ns"]) / 1e9,
            "bytes_sent_by_source": pub["bytes"],
            # CPU of every process of the cluster while this version moved (includes status polls)
            "cluster_cpu_s": cpu_s,
            "cpu_s_by_process": cpu_by,
            # per relay: when its last chunk reached it and its children, and the difference
            "relays": relays,
            "per_sink_s": times,
            # where the time went, per sink: when its lane got the last chunk, and how long the
            # assembly's verification and swap took after that
            "last_chunk_s": {n: (h["held"][str(v)]["last_chunk_ns"] - pub["t0_ns"]) / 1e9
                             for n, h in held.items() if "last_chunk_ns" in h["held"][str(v)]},
            "apply_s": {n: (h["held"][str(v)]["held_ns"] - h["held"][str(v)]["last_chunk_ns"]) / 1e9
                        for n, h in held.items() if "last_chunk_ns" in h["held"][str(v)]},
        })
        progress(f"v{v}: all {len(times)} rollouts hold it after {max(times.values()):.2f} s"
                 f"{' (warm-up)' if v == 1 else ''}")
    tx1 = cluster.node_tx_bytes(cluster.source)
    c1 = counters() if counters is not None else {}
    counted = [p["all_held_s"] for p in per_version if not p["warmup"]]
    return {
        "median_s": statistics.median(counted),
        "min_s": min(counted),
        "max_s": max(counted),
        "versions": per_version,
        "source_node_tx_bytes": None if tx0 is None or tx1 is None else tx1 - tx0,
        "counter_bytes": {k: c1[k] - c0[k] for k in c1 if k in c0},
        "cluster_cpu_s_median": statistics.median(p["cluster_cpu_s"] for p in per_version if not p["warmup"]),
    }


def relay_timing(cluster: RepCluster, version: int, t0_ns: int, held: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per relay, seconds from the source's start until the last chunk of `version` reached
    the relay (``last_in_s``) and the last of its children (``last_out_s``, the link included),
    and ``lag_ms`` between the two: what the relay's forwarding added, measured from outside."""
    arrived = {n: h["held"][str(version)].get("last_chunk_ns") for n, h in held.items()}
    for name in cluster.relays:
        st = cluster.status(name, timeout=1.0)
        arrived[name] = ((st.extra.get("arrivals") or {}).get(str(version)) or {}).get("last_chunk_ns") if st else None
    out = {}
    for name in cluster.relays:
        children = [arrived.get(c) for c in cluster.children_of(name)]
        if arrived[name] is None or not children or None in children:
            continue
        last_out = max(children)
        out[name] = {"last_in_s": (arrived[name] - t0_ns) / 1e9, "last_out_s": (last_out - t0_ns) / 1e9,
                     "lag_ms": (last_out - arrived[name]) / 1e6}
    return out


def _wait_sent(cluster: RepCluster, version: int, timeout_s: float) -> dict[str, Any]:
    """The source's record of `version` once its last put returned."""
    deadline = time.monotonic() + timeout_s
    while True:
        pub = cluster.published().get(str(version), {})
        if "sent_ns" in pub or time.monotonic() > deadline:
            if "sent_ns" not in pub:
                raise TimeoutError(f"the source did not finish sending v{version} in {timeout_s:.0f} s")
            return pub
        time.sleep(0.05)


def run_transfer(
    topology: Path,
    *,
    size_mib: float = 64.0,
    versions: int = 3,
    node_gbit: float = 1.0,
    uplink_gbit: float = 0.2,
    progress: Callable[[str], None] = lambda m: None,
) -> dict[str, Any]:
    """Tree vs star vs bound on the topology's emulated cluster (needs root for netns)."""
    base = transfer_topology(load_topology(topology), node_gbit, uplink_gbit, run="repbench")
    numel = int(size_mib * MIB) // 4
    size_bytes = numel * 4
    bound_s = size_bytes * 8 / (slowest_link_gbit(base) * 1e9)
    timeout_s = max(60.0, 10 * bound_s * 8)
    out: dict[str, Any] = {"size_bytes": size_bytes, "bound_s": bound_s, "emulate": base.emulate}
    netns = None
    tree_topo = without_roles(base, {"evaluator"})
    star_topo = without_roles(base, {"evaluator", "replicator"})
    try:
        with tempfile.TemporaryDirectory(prefix="dvla-bench-rep-") as tmp:
            tree = RepCluster(tree_topo, Path(tmp) / "tree", numel)
            progress(f"tree: starting {len(tree.plan.processes)} processes ({base.emulate})")
            tree.start()
            netns = tree.keep_netns()  # the star reuses the same namespaces and links
            try:
                est = simulate_broadcast(tree.topo, tree.plan, size_bytes)
                out["predicted_tree_s"], out["predicted_star_s"] = est.tree_s, est.star_s
                out["fanout"] = base.replication.fanout
                out["tree_children"] = {n: tree.children_of(n) for n in [tree.source, *tree.relays]}
                out["tree"] = measure(tree, versions, timeout_s, lambda m: progress("tree " + m))
            finally:
                tree.close()
            star = RepCluster(star_topo, Path(tmp) / "star", numel, netns=netns)
            progress(f"star: starting {len(star.plan.processes)} processes")
            star.start()
            try:
                out["star_children"] = {star.source: star.children_of(star.source)}
                out["star"] = measure(star, versions, timeout_s, lambda m: progress("star " + m))
            finally:
                star.close()
    finally:
        if netns is not None:
            netns.destroy()
    tree_s, star_s = out["tree"]["median_s"], out["star"]["median_s"]
    out["tree_s"], out["star_s"] = tree_s, star_s
    out["tree_over_bound"] = tree_s / bound_s
    out["star_over_tree"] = star_s / tree_s
    tx = out["tree"]["source_node_tx_bytes"]
    out["actor_uplink_bytes_over_s"] = None if tx is None else tx / (size_bytes * versions)
    sx = out["star"]["source_node_tx_bytes"]
    out["star_actor_uplink_bytes_over_s"] = None if sx is None else sx / (size_bytes * versions)
    return out


def run_training(
    topology: Path,
    *,
    encodings: tuple[str, ...] = ("full", "delta-bf16", "delta-topk"),
    max_env_steps: int = 150000,
    until_success: float = 0.8,
    seed: int = 1,
    base_port: int | None = None,
    progress: Callable[[str], None] = lambda m: None,
) -> dict[str, Any]:
    """`dvla up` once per encoding (same seed and budget); bytes per version and eval success."""
    base = load_topology(topology)
    port = base_port if base_port is not None else free_port_block()
    runs: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="dvla-bench-rep-train-") as tmp:
        for enc in encodings:
            topo = dataclasses.replace(base, run=f"rep-{enc}", replication=dataclasses.replace(base.replication, encoding=enc))
            path = Path(tmp) / f"{enc}.yaml"
            path.write_text(dump_topology_yaml(topo))
            cmd = [sys.executable, "-m", "dvla", "up", str(path), "--seed", str(seed), "--quiet", "--fresh", "--runs", tmp,
                   "--base-port", str(port), "--max-env-steps", str(max_env_steps), "--until-success", str(until_success)]
            progress(f"training with {enc}: {max_env_steps} env steps")
            t0 = time.monotonic()
            proc = subprocess.run(cmd, capture_output=True, text=True)
            run_dir = Path(tmp) / topo.run
            try:
                runs[enc] = _training_figures(run_dir, proc.returncode, time.monotonic() - t0)
            except (OSError, KeyError, ValueError, RuntimeError) as err:
                tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-8:])
                raise RuntimeError(f"{enc} training run failed ({err}); last output:\n{tail}") from None
            progress(f"{enc}: {runs[enc]['bytes_per_version']:.0f} bytes/version over {runs[enc]['versions']} versions, "
                     f"{runs[enc]['env_steps']} env steps, stopped by {runs[enc]['reason']}, final eval success {runs[enc]['final_success']}")
    full = runs.get("full", {}).get("bytes_per_version")
    out: dict[str, Any] = {"max_env_steps": max_env_steps, "until_success": until_success, "seed": seed, "runs": runs,
                           "snapshot_every": base.replication.snapshot_every, "topk_fraction": base.replication.topk_fraction}
    for enc in encodings:
        if enc != "full" and full:
            out[f"bytes_ratio_{enc.replace('-', '_')}"] = runs[enc]["bytes_per_version"] / full
            out[f"delta_bytes_ratio_{enc.replace('-', '_')}"] = (runs[enc]["delta_bytes_per_version"] or 0) / full
    return out


def _training_figures(run_dir: Path, exit_code: int, wall_s: float) -> dict[str, Any]:
    actor = next(iter(sorted((run_dir / "summaries").glob("actor-*.json"))), None)
    if actor is None:
        raise RuntimeError(f"training run in {run_dir} left no actor summary (exit {exit_code})")
    summ = json.loads(actor.read_text())
    extra = summ["extra"]
    versions = int(extra["published_version"])
    res = json.loads((run_dir / "result.json").read_text()) if (run_dir / "result.json").exists() else {}
    evals = res.get("evals", [])
    successes = [e.get("success_once") for e in evals if e.get("success_once") is not None]
    pub = extra.get("publish_bytes", {})
    sent = int(pub.get("full_bytes", 0)) + int(pub.get("delta_bytes", 0))
    return {
        "exit_code": exit_code,
        "wall_s": wall_s,
        "versions": versions,
        "bytes_published": sent,
        "bytes_per_version": sent / max(1, versions),
        "delta_bytes_per_version": (pub.get("delta_bytes", 0) / pub["delta_versions"]) if pub.get("delta_versions") else None,
        "full_versions": pub.get("full_versions"),
        "env_steps": res.get("env_steps"),
        "success_reached": bool(res.get("success_reached")),
        "reason": res.get("reason"),
        "final_success": successes[-1] if successes else None,
        "best_success": max(successes) if successes else None,
        "evals": [(e.get("env_steps"), e.get("success_once")) for e in evals],
    }


def run_bench(
    topology: Path,
    train_topology: Path,
    *,
    size_mib: float,
    versions: int,
    node_gbit: float,
    uplink_gbit: float,
    training_steps: int,
    progress: Callable[[str], None],
    transfer: bool = True,
) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
        "topology": str(topology),
        "node_gbit": node_gbit,
        "rack_uplink_gbit": uplink_gbit,
    }
    if transfer:
        doc.update(run_transfer(topology, size_mib=size_mib, versions=versions, node_gbit=node_gbit,
                                uplink_gbit=uplink_gbit, progress=progress))
    if training_steps > 0:
        train = run_training(train_topology, max_env_steps=training_steps, progress=progress)
        doc["training"] = train
        for k, v in train.items():
            if k.startswith("bytes_ratio_") or k.startswith("delta_bytes_ratio_"):
                doc[k] = v
    return doc


def format_table(doc: dict[str, Any]) -> str:
    def f(x: Any, nd: int = 2) -> str:
        return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))

    lines = []
    if "tree_s" in doc:
        lines += [
        f"version size          {doc['size_bytes'] / MIB:.0f} MiB  (links: node {doc['node_gbit']} Gbit/s, rack uplink {doc['rack_uplink_gbit']} Gbit/s)",
        f"bound_s               {f(doc['bound_s'])}",
        f"tree_s                {f(doc['tree_s'])}   (min {f(doc['tree']['min_s'])}, max {f(doc['tree']['max_s'])}; predicted {f(doc['predicted_tree_s'])})",
        f"star_s                {f(doc['star_s'])}   (min {f(doc['star']['min_s'])}, max {f(doc['star']['max_s'])}; predicted {f(doc['predicted_star_s'])})",
        f"cluster CPU/version   tree {f(doc['tree']['cluster_cpu_s_median'])} s, star {f(doc['star']['cluster_cpu_s_median'])} s"
        f"   ({os.cpu_count()} cores: CPU alone takes >= {f(doc['tree']['cluster_cpu_s_median'] / (os.cpu_count() or 1))} s per tree version)",
        f"tree_over_bound       {f(doc['tree_over_bound'])}   (goal <= 1.3)",
        f"star_over_tree        {f(doc['star_over_tree'])}   (goal >= 3)",
        f"actor_uplink_bytes/S  {f(doc['actor_uplink_bytes_over_s'])}   (goal <= fanout {doc['fanout']}; star: {f(doc['star_actor_uplink_bytes_over_s'])})",
        ]
    for k in ("bytes_ratio_delta_bf16", "bytes_ratio_delta_topk"):
        if k in doc:
            lines.append(f"{k:<22}{f(doc[k], 3)}")
    if "training" in doc:
        for enc, r in doc["training"]["runs"].items():
            lines.append(f"  {enc:<11} {r['versions']:>4} versions  {r['bytes_per_version']:>10.0f} B/version  "
                         f"{r['env_steps']} env steps ({r['reason']})  final success {f(r['final_success'])}  best {f(r['best_success'])}")
    return "\n".join(lines)

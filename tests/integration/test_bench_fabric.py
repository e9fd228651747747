"""`dvla bench fabric --quick`: the benchmark's machinery (processes, sessions, JSON), not its speed.

Runs the real command with tiny counts and checks that the JSON holds every headline figure as
a finite number computed from the raw figures beside it (their signs and sizes are the bench's to
report: tests/unit/test_bench_fabric_figures.py checks the formulas on known inputs), and that no
worker is left behind.
"""

from __future__ import annotations

import json
import math
import os
import platform
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.fabric import HEADLINE_KEYS

ROOT = Path(__file__).resolve().parents[2]


def finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def positive(x: object) -> bool:  # for counts: messages, samples, bytes
    return finite(x) and x > 0  # type: ignore[operator]


@pytest.mark.timeout(170)
def test_bench_fabric_quick_writes_every_figure(tmp_path: Path) -> None:
    out = tmp_path / "bench" / "fabric.json"
    proc = subprocess.run(
        [sys.executable, "-m", "dvla", "bench", "fabric", "--json", str(out), "--quick"],
        cwd=ROOT, capture_output=True, text=True, timeout=150,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    doc = json.loads(out.read_text())
    for key in HEADLINE_KEYS:
        assert finite(doc.get(key)), (key, doc.get(key))
    assert doc["quick"] is True and doc["shared_memory"] is False
    assert doc["keep_freed_buffers"] is (platform.libc_ver()[0] == "glibc")  # as roles do (dvla/fabric/heap.py)
    for label in ("64k", "1m"):
        e = doc["throughput"][label]
        assert positive(e["payload_bytes"]) and positive(e["messages"])
        assert finite(e["bytes_per_s"]) and finite(e["chunks_per_s"])
        assert len(e["rounds_bytes_per_s"]) == doc["config"]["rounds"]
        assert e["bytes_per_s"] == statistics.median(e["rounds_bytes_per_s"])
        assert isinstance(e["lost"], int) and 0 <= e["lost"] < e["messages"]  # a loss is reported, never a stall
        assert math.isclose(e["chunks_per_s"] * e["payload_bytes"], e["bytes_per_s"])
        assert doc[f"chunks_per_s_{label}"] == e["chunks_per_s"] and doc[f"mb_per_s_{label}"] == e["bytes_per_s"] / 1e6
    assert 60_000 < doc["throughput"]["64k"]["payload_bytes"] < 70_000
    assert 1_000_000 < doc["throughput"]["1m"]["payload_bytes"] < 1_100_000
    layouts = doc["ctrl_rtt_layouts"]
    # the links layout runs wherever it can be built (root + iproute2), loopback always
    assert set(layouts) == ({"loopback", "links"} if doc["links_layout"] == "used" else {"loopback"})
    assert doc["ctrl_rtt_layout"] == ("links" if "links" in layouts else "loopback")
    assert doc["ctrl_rtt"] == layouts[doc["ctrl_rtt_layout"]]
    for entry in layouts.values():
        assert entry["layout"]
        for phase in ("idle", "loaded", "loaded_shared"):
            r = entry[phase]
            assert finite(r["p50_ms"]) and finite(r["p99_ms"]) and r["p50_ms"] <= r["p99_ms"]
            assert positive(r["samples"])
        for phase in ("loaded", "loaded_shared"):
            assert finite(entry[phase]["flood_bytes_per_s"])
        assert entry["block_ratios"] and all(finite(r) for r in entry["block_ratios"])
    blocks = doc["loaded_over_idle_blocks"]
    assert blocks["min"] <= blocks["median"] <= blocks["max"] and len(blocks["values"]) == doc["config"]["rtt_blocks"]
    assert blocks["values"] == doc["ctrl_rtt"]["block_ratios"]
    # the headline figures from the phases they summarise
    head = doc["ctrl_rtt"]
    assert (doc["ctrl_rtt_p99_idle_ms"], doc["ctrl_rtt_p99_loaded_ms"], doc["ctrl_rtt_p99_loaded_shared_ms"]) == (
        head["idle"]["p99_ms"], head["loaded"]["p99_ms"], head["loaded_shared"]["p99_ms"])
    assert math.isclose(doc["loaded_over_idle"], head["loaded"]["p99_ms"] / head["idle"]["p99_ms"])
    assert math.isclose(doc["shared_over_separate"], head["loaded_shared"]["p99_ms"] / head["loaded"]["p99_ms"])
    if "links" in layouts:  # the plain-TCP control flooded the same data link
        links = layouts["links"]
        assert finite(links["loaded_tcp"]["flood_bytes_per_s"]) and links["loaded_tcp"]["flood"] == "tcp"
        assert links["loaded"]["flood"] == "fabric" and finite(doc["tcp_flood_over_idle"])
        assert math.isclose(doc["tcp_flood_over_idle"], links["loaded_tcp"]["p99_ms"] / links["idle_tcp"]["p99_ms"])
        assert links["loaded"]["auth"] == "identity" and links["loaded_noauth"]["auth"] == "none-data"
        assert finite(links["loaded_noauth"]["flood_bytes_per_s"]) and finite(doc["noauth_loaded_over_idle"])
        assert math.isclose(doc["noauth_loaded_over_idle"], links["loaded_noauth"]["p99_ms"] / links["idle_noauth"]["p99_ms"])
        # the ctrl path moved out of the flooding processes: a router and a status responder of
        # their own (no ctrl router in the sink, no status server in the source), the same flood
        wheres = ("processes", "core") if len(os.sched_getaffinity(0)) >= 2 else ("processes",)
        for where in wheres:
            loaded = links[f"loaded_apart_{where}"]
            assert loaded["apart"] == where and loaded["flood"] == "fabric" and loaded["auth"] == "identity"
            assert finite(loaded["flood_bytes_per_s"]) and finite(doc[f"apart_{where}_over_idle"])
            assert math.isclose(doc[f"apart_{where}_over_idle"], loaded["p99_ms"] / links[f"idle_apart_{where}"]["p99_ms"])
            assert set(links[f"cpus_apart_{where}"]) == {"sink", "source", "tool", "router", "responder"}
        assert "loaded_apart_core" in links or len(wheres) == 1
        if "core" in wheres:  # the ctrl path's processes on one CPU, the flooding ones on the others
            cpus = links["cpus_apart_core"]
            assert len(cpus["tool"]) == 1 and cpus["tool"] == cpus["router"] == cpus["responder"]
            assert cpus["sink"] == cpus["source"] and not set(cpus["sink"]) & set(cpus["tool"])
            assert set(cpus["sink"]) | set(cpus["tool"]) == os.sched_getaffinity(0)
        assert links["loaded"]["apart"] == ""  # the headline: the ctrl path through the sink and source, as in a run
        assert all(set(c) == os.sched_getaffinity(0) for c in links["cpus_apart_processes"].values())  # unpinned
        # the CPU control burns the flood's own CPU: the sink's and source's where they answer no queries
        assert finite(links["loaded_apart_processes"]["flood_cpu_cores"])
        assert links["loaded_cpu"]["hog_cores_asked"] == doc["flood_cpu_cores"] == links["loaded_apart_processes"]["flood_cpu_cores"]
        assert finite(links["loaded_cpu"]["hog_cores"])
        assert links["loaded_cpu"]["flood"] == "cpu" and links["loaded_cpu"]["flood_bytes_per_s"] == 0
        assert finite(doc["cpu_load_over_idle"])
        assert math.isclose(doc["cpu_load_over_idle"], links["loaded_cpu"]["p99_ms"] / links["idle_cpu"]["p99_ms"])
    for e in doc["throughput"].values():
        assert e["does"]  # each side's work, in words
        assert finite(e["pub_cpu_us_per_msg"]) and finite(e["sub_cpu_us_per_msg"])
    assert "ctrl RTT" in proc.stdout and "chunks/s" in proc.stdout
    alive = [pid for pid in doc["worker_pids"] if Path(f"/proc/{pid}").exists() and not _zombie(pid)]
    # 2 sizes x (publisher, subscriber) + 3 auth modes x (publisher, subscriber) + per layout 2 x (sink, source,
    # tool), the links layout three more (without authentication; plain TCP; the CPU control, with its hogs)
    # and the ctrl-apart controls (sink, source, tool, router, responder each)
    apart = 5 * sum(f"loaded_apart_{w}" in layouts.get("links", {}) for w in ("processes", "core"))
    assert len(doc["worker_pids"]) == 4 + 6 + 6 * len(layouts) + (9 + 2) * ("links" in layouts) + apart and alive == [], alive
    auth = doc["auth"]
    assert set(auth["data"]) == {"none", "tag", "identity"}
    none = auth["data"]["none"]
    for mode in ("tag", "identity"):
        d = auth["data"][mode]
        assert finite(d["throughput_ratio"]) and finite(d["chunks_per_s"])
        assert math.isclose(d["throughput_ratio"], d["chunks_per_s"] / none["chunks_per_s"])
        assert math.isclose(d["extra_cpu_us_per_chunk"], d["pub_cpu_us_per_chunk"] + d["sub_cpu_us_per_chunk"]
                            - none["pub_cpu_us_per_chunk"] - none["sub_cpu_us_per_chunk"], abs_tol=1e-9)
        assert isinstance(d["lost"], int) and d["lost"] >= 0
        w = auth["weights"][mode]
        assert finite(w["seal_cpu_s"]) and finite(w["open_cpu_s"])
    assert doc["auth_throughput_ratio"] == auth["data"]["identity"]["throughput_ratio"]
    assert doc["auth_extra_cpu_us_per_chunk"] == auth["data"]["identity"]["extra_cpu_us_per_chunk"]
    assert doc["actor_cpu_us_per_auth_chunk"] == auth["data"]["identity"]["sub_cpu_us_per_chunk"]
    assert "authentication" in proc.stdout
    if doc["netns"]:  # the namespaces of the links layout are gone again
        assert all(not Path(f"/var/run/netns/{ns}").exists() for ns in doc["netns"]), doc["netns"]


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return True

"""`dvla bench swimlane --quick`: the benchmark's machinery on real runs (orchestrator, role
processes, ManiSkill, Zenoh), not its speed.

Checks that the JSON holds every headline figure as a finite number computed from the runs
beside it (their signs and sizes are the bench's to report), that each run measured a
real window (steps, versions, lanes, placement as configured), that the lock-step baseline is
really lock-step (every chunk it learned from was sampled with the newest weights), that the
chunk accounting closes, and that no role process is left behind.
"""

from __future__ import annotations

import json
import math
import platform
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.swimlane import HEADLINE_KEYS

ROOT = Path(__file__).resolve().parents[2]


def finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def median(xs: object) -> float:
    """The median of the figures that were measured (as the bench takes it: None left out)."""
    return statistics.median(x for x in xs if x is not None)  # type: ignore[attr-defined]


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_bench_swimlane_quick_writes_every_figure(tmp_path: Path) -> None:
    out = tmp_path / "bench" / "swimlane.json"
    runs = tmp_path / "runs"
    proc = subprocess.run(
        [sys.executable, "-m", "dvla", "bench", "swimlane", "--json", str(out), "--quick", "--runs", str(runs)],
        cwd=ROOT, capture_output=True, text=True, timeout=840,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    doc = json.loads(out.read_text())
    for key in HEADLINE_KEYS:
        assert key in doc, key
    for key in ("sim_only_sps", "async_sps", "async_over_sim_only", "balanced_async_sps", "sync_sps",
                "async_over_sync", "infer_p99_ms_no_swap", "learner_batch_s", "rollout_batch_s"):
        assert finite(doc[key]), (key, doc[key])
    assert finite(doc["rss_growth_pct"]) and -50 < doc["rss_growth_pct"] < 500
    # split placement (two cores here): the simulators alone on core 0, everything else on core 1;
    # the learner's share of a core is still measured
    assert doc["default_placement"] == "split"
    assert doc["ceiling_from_learner"] == 1.0
    default_wl = doc["workloads"]["default"]
    learn = [next(lanes["learn"]["utilisation"] for lanes in p["async"]["lanes"].values() if "learn" in lanes)
             for p in default_wl["runs"]]
    assert finite(default_wl["learner_core_share"]) and default_wl["learner_core_share"] == pytest.approx(median(learn))
    # what a step costs in each mode (the median over its runs), and the ratio at equal step cost
    runs_of = {"sim_only": [p["sim_only"] for p in default_wl["runs"]] + [default_wl["closing_sim_only"]],
               "async": [p["async"] for p in default_wl["runs"]]}
    for mode, cpu in default_wl["sim_cpu"].items():
        assert all(finite(cpu[k]) for k in ("cores", "ms_per_step", "env_step_ms")), (mode, cpu)
        assert cpu["cores"] == pytest.approx(median(r.get("sim_cpu_cores") for r in runs_of[mode])), (mode, cpu)
        assert cpu["ms_per_step"] == pytest.approx(median(r.get("sim_cpu_ms_per_step") for r in runs_of[mode])), (mode, cpu)
        assert cpu["env_step_ms"] == pytest.approx(median(r.get("env_step_cpu_ms") for r in runs_of[mode])), (mode, cpu)
    assert finite(doc["step_cost_ratio"]) and doc["step_cost_ratio"] == pytest.approx(median(default_wl["step_cost_ratios"]))
    assert doc["async_over_sim_only_equal_step_cost"] == pytest.approx(doc["async_over_sim_only"] * doc["step_cost_ratio"])
    assert finite(doc["policy_lag_mean"]) and doc["policy_lag_mean"] >= 0
    assert finite(doc["policy_lag_p99"]) and doc["policy_lag_p99"] >= doc["policy_lag_mean"] - 1e-9
    # A swap batch needs a version to land inside the short window; when one did, its p99 is real.
    assert doc["infer_swap_batches"] >= 0
    if doc["infer_swap_batches"]:
        assert finite(doc["infer_p99_ms_during_swap"])
    assert doc["profile"]["quick"] is True and doc["command"].startswith("dvla bench swimlane")
    assert {"python", "cpus", "load_avg_start", "load_avg_end"} <= set(doc["machine"])

    default, balanced = doc["workloads"]["default"], doc["workloads"]["balanced"]
    for wl in (default, balanced):
        for pair in wl["runs"]:
            for mode, run in pair.items():
                assert run["error"] is None, (mode, run)
                acct = run["accounting"]
                assert acct["unaccounted"] == 0, (mode, acct)
                assert finite(run["window_s"])
    # the async run is bracketed by a sim_only run before and a closing one after it
    assert default["closing_sim_only"]["error"] is None
    before, after = default["sim_only_sps_runs"]
    assert finite(before) and finite(after)
    assert default["sim_only_baselines"] == [pytest.approx((before + after) / 2)]
    assert doc["async_over_sim_only"] == pytest.approx(doc["async_sps"] / doc["sim_only_sps"])
    sim_only = default["runs"][0]["sim_only"]
    assert sim_only["consumed_sps"] == 0 and sim_only["accounting"]["produced"] == 0  # nothing shipped
    assert all(lanes["sim"]["items"] > 0 and finite(lanes["sim"]["utilisation"])
               for n, lanes in sim_only["lanes"].items() if n.startswith("rollout"))
    async_default = default["runs"][0]["async"]
    assert async_default["versions"] >= 1 and async_default["policy_lag"]["chunks"] > 0
    lat = async_default["infer_latency"]
    assert lat["no_swap"]["n"] > 0
    # every batch is counted once in each split: by its start, and by what overlapped it
    assert lat["swap"]["n"] + lat["no_swap"]["n"] == lat["overlap"]["n"] + lat["no_overlap"]["n"]
    assert async_default["rss"]["roles"] and all(r["samples"] >= 2 for r in async_default["rss"]["roles"].values())
    assert not any(n.startswith("evaluator") for n in async_default["lanes"])
    for name, placement in async_default["placement"].items():
        assert placement["cpus"] == [1], (name, placement)
        sim_core = [0] if name.startswith("rollout") else [1]
        assert all(cores == (sim_core if lane == "sim" else [1]) for lane, cores in placement["lanes"].items()), placement

    sync = balanced["runs"][0]["sync"]
    assert sync["versions"] >= 1
    # Lock-step: every chunk the learner got was sampled with the newest published weights.
    assert sync["policy_lag"]["chunks"] > 0 and sync["policy_lag"]["max"] == 0, sync["policy_lag"]
    for run in (sync, balanced["runs"][0]["async"]):
        for name, placement in run["placement"].items():
            want = [1] if name.startswith("actor") else [0]
            assert placement["cpus"] == want, (name, placement)
            assert placement["torch_threads"] == {"intra": 1, "interop": 1}
            assert placement["keep_freed_buffers"] is (platform.libc_ver()[0] == "glibc")  # dvla/fabric/heap.py
    assert isinstance(balanced["balanced_within_20pct"], bool)

    leftover = subprocess.run(["pgrep", "-f", str(runs)], capture_output=True, text=True).stdout.split()
    assert leftover == [], leftover

"""`dvla bench learners --quick`: the benchmark's machinery (rank processes, a real gloo group,
DDP with the timing hook, JSON), not its speed.

Runs the real command with tiny counts and checks that both rank counts ran every update, that
the two-rank group really all-reduced gradients, that every figure is computed from the ranks'
timings beside it (their sizes are the bench's to report), that both ranks end with
bit-identical parameters, and that no rank process is left behind.
"""

from __future__ import annotations

import json
import math
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def positive(x: object) -> bool:  # for counts
    return finite(x) and x > 0  # type: ignore[operator]


@pytest.mark.timeout(120)
def test_bench_learners_quick_measures_both_rank_counts(tmp_path: Path) -> None:
    out = tmp_path / "bench" / "learners.json"
    proc = subprocess.run(
        [sys.executable, "-m", "dvla", "bench", "learners", "--json", str(out), "--quick", "--updates", "2"],
        cwd=ROOT, capture_output=True, text=True, timeout=100,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    doc = json.loads(out.read_text())
    assert doc["quick"] is True and doc["command"].startswith("dvla bench learners")
    assert doc["config"]["ranks"] == [1, 2] and doc["config"]["updates"] == 2
    assert doc["workload"]["policy"] == "tiny-vla" and positive(doc["workload"]["parameters"])
    assert {"samples_per_s", "allreduce", "comm_share", "params_identical"} <= set(doc["method"])
    assert set(doc["runs"]) == {"1", "2"}
    for world, run in doc["runs"].items():
        assert run["ranks"] == int(world) and len(run["per_rank"]) == int(world)
        assert finite(run["samples_per_s"]) and finite(run["update_s_median"])
        assert len(run["round_samples_per_s"]) == 2  # --quick: one update per round
        for rank in run["per_rank"]:
            assert len(rank["update_s"]) == len(rank["comm_s"]) == 2
            assert all(finite(c) and finite(u) for c, u in zip(rank["comm_s"], rank["update_s"]))
        # the figures from the ranks' timings beside them (tests/unit/test_bench_learners_figures.py: the formulas)
        update = [u for rank in run["per_rank"] for u in rank["update_s"]]
        comm = [c for rank in run["per_rank"] for c in rank["comm_s"]]
        updates = int(world) * doc["config"]["updates"]
        assert run["samples_per_s"] == pytest.approx(updates * doc["config"]["batch"] / run["wall_s"])
        assert run["update_s_median"] == pytest.approx(statistics.median(update))
        assert run["allreduce_s_per_update"] == pytest.approx(sum(comm) / updates)
        assert finite(run["comm_share"]) and run["comm_share"] == pytest.approx(sum(comm) / sum(update))
        assert doc["figures"][f"samples_per_s_{world}"] == run["samples_per_s"]
    one, two = doc["runs"]["1"], doc["runs"]["2"]
    assert one["allreduce_s_per_update"] == 0 and one["allreduces_per_update"] == 0  # a group of one: no DDP
    assert finite(two["allreduce_s_per_update"]) and finite(two["comm_share"])
    # one all-reduce per gradient bucket of every minibatch step, the whole gradient each step
    assert two["allreduces_per_update"] >= doc["config"]["minibatches"] * doc["config"]["update_epochs"]
    assert two["grad_bytes_per_update"] >= 4 * doc["workload"]["parameters"] * doc["config"]["minibatches"]
    speedup = doc["ratios"]["speedup_2_over_1"]
    assert speedup == pytest.approx(two["samples_per_s"] / one["samples_per_s"])
    assert doc["ratios"]["scaling_efficiency_2"] == pytest.approx(speedup / 2)
    assert doc["params_identical"] is True and two["params_identical"] is True
    assert len({r["checksum"] for r in two["per_rank"]}) == 1
    assert "params identical across ranks: True" in proc.stdout
    pids = [r["pid"] for run in doc["runs"].values() for r in run["per_rank"]]
    assert len(set(pids)) == 3
    alive = [pid for pid in pids if Path(f"/proc/{pid}").exists() and not _zombie(pid)]
    assert alive == [], alive


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return True

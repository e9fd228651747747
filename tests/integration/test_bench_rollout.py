"""`dvla bench rollout` end to end at tiny windows: real rollouts (in-process envs and two simulator
workers) in fresh processes, the simulators alone and the policy alone, JSON and PNG written."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@pytest.mark.timeout(600)
def test_bench_rollout_sweeps_workers_against_its_baselines(tmp_path: Path) -> None:
    out = tmp_path / "rollout.json"
    p = subprocess.run(
        [sys.executable, "-m", "dvla", "bench", "rollout", "topologies/local.yaml", "--workers", "0,2",
         "--envs-per-worker", "2", "--repeats", "1", "--warmup", "1", "--window", "3", "--json", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=580,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    doc = json.loads(out.read_text())
    rows = {r["workers"]: r for r in doc["rows"]}
    assert sorted(rows) == [0, 2]
    assert rows[0]["envs"] == 2 and rows[2]["envs"] == 4 and rows[2]["batch"] == 2
    for w, r in rows.items():
        assert finite(r["sim_only_sps"]) and finite(r["train_sps"]) and finite(r["policy_sps"]), r
        # each figure from the runs beside it (--repeats 1: one run each)
        runs = doc["runs"][f"W{w}-e2"]
        assert (r["sim_only_sps"], r["train_sps"]) == (runs["sim_only"][0]["sps"], runs["train"][0]["sps"])
        assert r["policy_sps"] == doc["policy"][str(r["batch"])]["sps"]
        assert r["train_over_sim"] == pytest.approx(r["train_sps"] / r["sim_only_sps"])
        assert finite(r["step_cost_ratio"])
        assert r["step_cost_ratio"] == pytest.approx(runs["train"][0]["env_step_cpu_ms"] / runs["sim_only"][0]["env_step_cpu_ms"])
    assert len(rows[2]["worker_busy"]) == 2 and rows[0]["worker_busy"] == []
    train = doc["runs"]["W2-e2"]["train"][0]
    assert train["chunks_shipped"] > 0 and train["env_groups"] == [2, 2] and not train.get("error")
    assert doc["runs"]["W2-e2"]["sim_only"][0]["chunks_shipped"] == 0  # the simulators alone ship nothing
    assert rows[2]["sim_scaling"] == pytest.approx(1.0)  # the smallest W > 0 is the scaling's base
    assert Path(doc["plot"]).is_file() and Path(doc["plot"]).stat().st_size > 1000
    assert "sim_scaling_w2" in doc and "train_over_sim_equal_step_cost_w2" in doc

"""End to end on LIBERO: a short `dvla up` of topologies/local-libero.yaml (shortened): the
rollout renders LIBERO-spatial, the actor trains tiny-vla, new versions reach the rollout and the
evaluator reports success per task in evals.csv. Skipped with the reason when hf-libero or the
assets are absent."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from .libero_needs import ROOT, libero_assets, requires_libero
from .test_up_e2e import free_port_block, pids_of_run

pytestmark = requires_libero


@pytest.mark.timeout(600)
def test_up_libero_trains_and_evaluates_per_task(tmp_path: Path) -> None:
    doc = yaml.safe_load((ROOT / "topologies" / "local-libero.yaml").read_text())
    task = doc["task"]
    task["libero"]["assets"] = str(libero_assets())
    task.update(max_episode_steps=20, chunk_steps=10)
    task["ppo"].update(batch_steps=40, minibatches=2, update_epochs=1)
    task["eval"].update(episodes=2, every_versions=1)
    topo = tmp_path / "libero.yaml"
    topo.write_text(yaml.safe_dump(doc))
    runs = tmp_path / "runs"
    proc = subprocess.run(
        [sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs), "--base-port", str(free_port_block()),
         "--max-env-steps", "160", "--quiet"],
        cwd=ROOT, capture_output=True, text=True, timeout=540,
    )
    run_dir = runs / "local-libero"
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "max_env_steps" and result["final_env_steps"] >= 160
    assert result["accounting"]["unaccounted"] == 0

    summaries = {p.stem: json.loads(p.read_text()) for p in (run_dir / "summaries").glob("*.json")}
    assert summaries["actor-node0-0"]["extra"]["published_version"] >= 3
    rollout = summaries["rollout-node0-0"]
    assert rollout["error"] is None and rollout["extra"]["chunks_shipped"] > 0
    assert rollout["policy_version"] >= 2, "no version after the first reached the rollout"

    with open(run_dir / "evals.csv") as f:
        rows = list(csv.DictReader(f))
    whole = [r for r in rows if r["task"] == "all"]
    assert whole, rows
    per_task = [r for r in rows if r["task"] != "all" and r["version"] == whole[0]["version"]]
    # two episodes from consecutive seeds: one of each task
    assert sorted(r["task"] for r in per_task) == ["libero_spatial/0", "libero_spatial/1"]
    assert all(int(r["episodes"]) == 1 and 0.0 <= float(r["success_once"]) <= 1.0 for r in per_task)
    assert pids_of_run(run_dir) == []

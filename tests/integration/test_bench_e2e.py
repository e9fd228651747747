"""`dvla bench e2e`: the harness (seeds x modes interleaved, result.json and evals.csv read back,
per-mode spread and learning curves), not the learning: tiny.yaml stops at its step budget."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.e2e import curve_quantiles
from benchmarks.ports import free_port_block

ROOT = Path(__file__).resolve().parents[2]


def test_curve_quantiles_hold_the_last_value_of_stopped_runs():
    a = [{"env_steps": 4000, "success_once": 0.25}, {"env_steps": 12000, "success_once": 0.75}]
    b = [{"env_steps": 6000, "success_once": 0.5}]
    curve = curve_quantiles([a, b, []], step=4000)
    assert [p["env_steps"] for p in curve] == [4000, 8000, 12000]
    assert curve[0]["median"] == pytest.approx(0.125)  # b has no eval yet at 4000: 0
    assert curve[1]["median"] == pytest.approx(0.375) and curve[2]["median"] == pytest.approx(0.625)
    assert all(p["p25"] <= p["median"] <= p["p75"] for p in curve)


def test_the_qualifying_versions_env_steps_come_from_versions_csv(tmp_path: Path) -> None:
    from benchmarks.e2e import _curve, _version_steps

    (tmp_path / "versions.csv").write_text("1,abc,full,1600,1.0,7\n2,def,full,3200,2.0,7\n")
    assert _version_steps(tmp_path / "versions.csv") == {1: 1600, 2: 3200}
    assert _version_steps(tmp_path / "missing.csv") == {}
    (tmp_path / "evals.csv").write_text(
        "time_s,version,env_steps,success_once,success_at_end,return_mean,episodes,success_low,success_high,task\n"
        "10.0,2,4000,0.5,0.5,1.0,4,0.1,0.9,all\n10.0,2,4000,1.0,,,2,0.3,1.0,libero_spatial/0\n")
    assert _curve(tmp_path / "evals.csv", 4.0) == [{"env_steps": 4000, "train_s": 6.0, "version": 2, "success_once": 0.5}]


def test_bench_e2e_rejects_unknown_modes():
    proc = subprocess.run([sys.executable, "-m", "dvla", "bench", "e2e", "topologies/tiny.yaml", "--modes", "lockstep"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "--modes" in proc.stdout + proc.stderr


@pytest.mark.timeout(420)
def test_bench_e2e_runs_both_modes_per_seed(tmp_path: Path) -> None:
    out = tmp_path / "e2e.json"
    text = (ROOT / "topologies/tiny.yaml").read_text()
    assert "  algorithm: ppo\n" in text
    # frequent short evaluations: a curve within the budget; episodes end at success, as in local.yaml
    topo = tmp_path / "tiny-evals.yaml"
    evals = "  eval: {episodes: 4, every_versions: 1, full_episodes: false}\n"
    topo.write_text(text.replace("  algorithm: ppo\n", "  algorithm: ppo\n" + evals, 1))
    proc = subprocess.run(
        [sys.executable, "-m", "dvla", "bench", "e2e", str(topo), "--seeds", "3", "--modes", "async,sync",
         "--json", str(out), "--base-port", str(free_port_block()), "--final-eval", "3"],
        cwd=ROOT, capture_output=True, text=True, timeout=390,  # ~3 min on a quiet 2-core machine
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    doc = json.loads(out.read_text())
    assert [(r["seed"], r["mode"]) for r in doc["runs"]] == [(3, "async"), (3, "sync")]
    for r in doc["runs"]:
        assert r["exit_code"] == 0 and r["reason"] == "max_env_steps" and not r["success"], r
        assert r["accounting"]["unaccounted"] == 0
        assert r["curve"] and all(0.0 <= p["success_once"] <= 1.0 for p in r["curve"]), r
        assert [p["env_steps"] for p in r["curve"]] == sorted(p["env_steps"] for p in r["curve"])
        # each evaluated version's own env steps (versions.csv): at most what was learned when its evaluation ended
        assert all(isinstance(p["policy_env_steps"], int) and p["policy_env_steps"] <= p["env_steps"] for p in r["curve"]), r
        # the final checkpoint on 3 episodes of its own seeds, each to the time limit
        final = r["final_eval"]
        assert (final["episodes"], final["seed"]) == (3, 9_003_000) and final["version"] >= 1, final
        assert final["env_steps"] == 3 * 50 and 0.0 <= final["success_once"] <= 1.0, final
    assert set(doc["modes"]) == {"async", "sync"}
    for m in doc["modes"].values():
        assert m["runs"] == 1 and m["successes"] == 0 and m["curve"]
    assert "async: 0/1 reached the target" in proc.stdout
    assert "final v" in proc.stdout and "on 3" in proc.stdout

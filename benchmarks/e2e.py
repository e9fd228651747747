"""End-to-end learning benchmark: `dvla up TOPOLOGY` once per seed and mode, each to its success
target. Modes run interleaved (seed 1 async, seed 1 sync, seed 2 async, ...) so both see the
same machine. Per run: env steps and wall time from the first env step to the stop rule's last
qualifying eval, start-up time, training env steps/s (from result.json), the env steps the last
qualifying version had been trained on (``policy_env_steps``, from versions.csv: the run's own
figure also counts what was learned while that evaluation was played) and the learning curve
(every evaluation's success rate by env steps and by seconds of training, from evals.csv). Per
mode: median and spread across seeds, and the curve's median and quartiles across seeds on a grid
of env steps."""

from __future__ import annotations

import csv
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from benchmarks.final_eval import evaluate_run, fresh_seed

#: env steps between the points of the summarised learning curve
CURVE_STEP = 8000


def run_seeds(topology: Path, seeds: list[int], base_port: int, extra: list[str],
              modes: tuple[str, ...] = ("async",), final_eval: int = 0) -> dict[str, Any]:
    """``final_eval`` > 0: each run's final policy is also played on that many episodes none of
    its evaluations played (benchmarks/final_eval.py), as ``final_eval`` of the run."""
    runs = []
    with tempfile.TemporaryDirectory(prefix="dvla-bench-e2e-") as tmp:
        for seed in seeds:
            for mode in modes:
                runs.append(_one_run(topology, seed, mode, Path(tmp), base_port, extra, final_eval))
    by_mode = {m: _summary([r for r in runs if r["mode"] == m]) for m in modes}
    first = by_mode[modes[0]]
    return {
        "topology": str(topology),
        "runs": runs,
        "modes": by_mode,
        # the first mode's figures at the top level, as before modes existed
        **{k: first[k] for k in ("successes", "train_s_median", "env_steps_median", "train_steps_per_s_median")},
    }


def _one_run(topology: Path, seed: int, mode: str, tmp: Path, base_port: int, extra: list[str],
             final_eval: int = 0) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "dvla", "up", str(topology), "--seed", str(seed), "--mode", mode, "--quiet",
           "--fresh", "--runs", str(tmp), "--base-port", str(base_port), *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    result_files = list(tmp.glob("*/result.json"))
    res = json.loads(result_files[0].read_text()) if result_files else {}
    curve = _curve(result_files[0].parent / "evals.csv", res.get("startup_s")) if result_files else []
    trained = _version_steps(result_files[0].parent / "versions.csv") if result_files else {}
    for point in curve:  # what the evaluated version had learned from (env_steps: when its evaluation ended)
        point["policy_env_steps"] = trained.get(point["version"])
    qualifying = curve[-1]["version"] if curve and res.get("success_reached") else None
    independent = (evaluate_run(result_files[0].parent, final_eval, fresh_seed(seed))
                   if final_eval > 0 and result_files else None)
    for f in result_files:
        f.unlink()
    return {
        "seed": seed,
        "mode": mode,
        "exit_code": proc.returncode,
        "reason": res.get("reason"),
        "success": bool(res.get("success_reached")),
        "env_steps": res.get("env_steps"),
        "policy_env_steps": trained.get(qualifying) if qualifying is not None else None,
        "train_s": res.get("train_s"),
        "startup_s": res.get("startup_s"),
        "train_steps_per_s": res.get("train_steps_per_s"),
        "evals": len(res.get("evals", [])),
        "curve": curve,
        "accounting": res.get("accounting"),
        "final_eval": independent,
    }


def _curve(evals_csv: Path, startup_s: float | None) -> list[dict[str, float]]:
    """(env steps, seconds of training, version, success_once) of every evaluation of a run (its
    whole-evaluation rows; per-task rows are left out)."""
    try:
        with open(evals_csv) as f:
            rows = [r for r in csv.DictReader(f) if r.get("task", "all") in ("all", "", None)]
    except OSError:
        return []
    t0 = startup_s or 0.0
    return [{"env_steps": int(r["env_steps"]), "train_s": round(float(r["time_s"]) - t0, 2),
             "version": int(r["version"]), "success_once": float(r["success_once"])} for r in rows]


def _version_steps(versions_csv: Path) -> dict[int, int]:
    """version -> env steps learned when the actor published it (versions.csv: version, checksum,
    encoding, env_steps, time, pid)."""
    try:
        with open(versions_csv) as f:
            return {int(row[0]): int(row[3]) for row in csv.reader(f) if len(row) >= 4 and row[0].isdigit()}
    except (OSError, ValueError):
        return {}


def _spread(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def _summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in runs if r["success"]]
    return {
        "runs": len(runs),
        "successes": len(ok),
        "train_s_median": statistics.median(r["train_s"] for r in ok) if ok else None,
        "env_steps_median": statistics.median(r["env_steps"] for r in ok) if ok else None,
        "policy_env_steps": _spread([r["policy_env_steps"] for r in ok if r["policy_env_steps"] is not None]),
        "train_steps_per_s_median": statistics.median(r["train_steps_per_s"] for r in ok) if ok else None,
        "env_steps": _spread([r["env_steps"] for r in ok]),
        "train_s": _spread([r["train_s"] for r in ok]),
        "train_steps_per_s": _spread([r["train_steps_per_s"] for r in ok]),
        "curve": curve_quantiles([r["curve"] for r in runs]),
    }


def curve_quantiles(curves: list[list[dict[str, float]]], step: int = CURVE_STEP) -> list[dict[str, float]]:
    """Median and quartiles across runs of the success rate at every `step` env steps: each run's
    latest evaluation at or before that point (a run that stopped holds its last value)."""
    curves = [c for c in curves if c]
    if not curves:
        return []
    end = max(c[-1]["env_steps"] for c in curves)
    out = []
    for x in range(step, end + step, step):
        values = []
        for c in curves:
            seen = [p["success_once"] for p in c if p["env_steps"] <= x]
            values.append(seen[-1] if seen else 0.0)
        q = statistics.quantiles(values, n=4, method="inclusive") if len(values) > 1 else values * 3
        out.append({"env_steps": x, "p25": q[0], "median": statistics.median(values), "p75": q[2]})
    return out

"""End-to-end learning benchmark: `dvla up TOPOLOGY` once per seed, each to its success target;
reports per seed the env steps and wall time from the first env step to the third consecutive
eval at or above the target, start-up time, and training env steps/s (from each run's
result.json)."""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any


def run_seeds(topology: Path, seeds: list[int], base_port: int, extra: list[str]) -> dict[str, Any]:
    runs = []
    with tempfile.TemporaryDirectory(prefix="dvla-bench-e2e-") as tmp:
        for seed in seeds:
            cmd = [sys.executable, "-m", "dvla", "up", str(topology), "--seed", str(seed), "--quiet", "--fresh",
                   "--runs", tmp, "--base-port", str(base_port), *extra]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            result_files = list(Path(tmp).glob("*/result.json"))
            res = json.loads(result_files[0].read_text()) if result_files else {}
            for f in result_files:
                f.unlink()
            runs.append({
                "seed": seed,
                "exit_code": proc.returncode,
                "reason": res.get("reason"),
                "success": bool(res.get("success_reached")),
                "env_steps": res.get("env_steps"),
                "train_s": res.get("train_s"),
                "startup_s": res.get("startup_s"),
                "train_steps_per_s": res.get("train_steps_per_s"),
                "evals": len(res.get("evals", [])),
                "accounting": res.get("accounting"),
            })
    ok = [r for r in runs if r["success"]]
    return {
        "topology": str(topology),
        "runs": runs,
        "successes": len(ok),
        "train_s_median": statistics.median(r["train_s"] for r in ok) if ok else None,
        "env_steps_median": statistics.median(r["env_steps"] for r in ok) if ok else None,
        "train_steps_per_s_median": statistics.median(r["train_steps_per_s"] for r in ok) if ok else None,
    }

"""PNG plots of a run from its CSV files: eval success and env steps/s over time."""

from __future__ import annotations

import csv
from pathlib import Path


def _read(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def plot_run(run_dir: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = _read(run_dir / "metrics.csv")
    evals = [r for r in _read(run_dir / "evals.csv") if r.get("task", "all") == "all"]  # not per-task rows
    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    if evals:
        t = [float(r["time_s"]) for r in evals]
        ax1.plot(t, [float(r["success_once"]) for r in evals], "o-", label="success_once")
        ax1.plot(t, [float(r["success_at_end"]) for r in evals], "s--", label="success_at_end")
        ax1.legend(loc="lower right")
    else:
        # A run without evaluations (no evaluator, or stopped before the first one) says so
        # instead of drawing an empty axis with an empty legend.
        ax1.text(0.5, 0.5, "no evaluations in this run", ha="center", va="center", transform=ax1.transAxes)
    ax1.set_ylabel("eval success")
    ax1.set_ylim(-0.02, 1.02)
    ax1.grid(alpha=0.3)
    if metrics:
        t = [float(r["time_s"]) for r in metrics]
        ax2.plot(t, [float(r["steps_per_s"]) for r in metrics], label="learner env steps/s")
        ax3.plot(t, [float(r["policy_lag_mean"]) for r in metrics], label="policy lag (versions)")
    ax2.set_ylabel("env steps/s")
    ax2.grid(alpha=0.3)
    ax3.set_ylabel("policy lag")
    ax3.set_xlabel("time since start (s)")
    ax3.grid(alpha=0.3)
    fig.suptitle(f"dvla run {run_dir.name}")
    fig.tight_layout()
    out = run_dir / "plots" / "training.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out

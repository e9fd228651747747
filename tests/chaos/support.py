"""What the chaos and hostile-traffic tests share: a free port block, `dvla up` in the background,
and a signed view of the run's status (the test harness holds the run's secret; attackers do not)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

from benchmarks.ports import free_port_block  # noqa: F401  (tests import it from here)

ROOT = Path(__file__).resolve().parents[2]


def start_up(topology: str, runs: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "dvla", "up", topology, "--runs", str(runs), "--quiet", *extra],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )


def state(run_dir: Path) -> dict[str, Any]:
    try:
        return json.loads((run_dir / "state.json").read_text())
    except (OSError, ValueError):
        return {}


def wait_for(pred: Callable[[], Any], timeout: float, what: str, up: subprocess.Popen | None = None) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if up is not None and up.poll() is not None:
            raise AssertionError(f"dvla up exited early ({up.returncode}) while waiting for {what}")
        got = pred()
        if got:
            return got
        time.sleep(0.5)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def harness_fabric(run_dir: Path) -> Any:
    """A ctrl-plane client with the run's secret and operator identity (the harness, not an attacker)."""
    from dvla.orchestrator.run import state_fabric

    return state_fabric(state(run_dir), "test-harness")


def statuses(fabric: Any, timeout: float = 2.0) -> dict[str, Any]:
    from dvla.fabric.messages import RoleStatus

    return {m.name: m for _s, m in fabric.query(fabric.keys.status_all(), expect=RoleStatus, timeout=timeout)}


def pids_of_run(run_dir: Path) -> list[str]:
    import os

    out = subprocess.run(["pgrep", "-f", str(run_dir)], capture_output=True, text=True).stdout.split()
    return [p for p in out if p != str(os.getpid())]

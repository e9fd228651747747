"""Supervision: kill -9 a rollout, the actor and the replicator of a running `dvla up`, one at a
time. Each is restarted, the run keeps learning until `dvla down` stops it, policy versions never go backwards
(the restarted actor resumes from its checkpoint and numbers above every replica), and
`dvla status` shows the restarts."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .test_up_e2e import ROOT, dvla, free_port_block, pids_of_run


def _state(run_dir: Path) -> dict:
    try:
        return json.loads((run_dir / "state.json").read_text())
    except (OSError, ValueError):
        return {}


def _status(runs: Path) -> dict:
    st = dvla("status", "tiny", "--runs", str(runs), "--format", "json", timeout=60)
    return json.loads(st.stdout) if st.returncode == 0 else {}


def _wait(pred, timeout: float, what: str, up: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if up.poll() is not None:
            raise AssertionError(f"dvla up exited early while waiting for {what}")
        if pred():
            return
        time.sleep(2.5)  # each check starts a `dvla status` (~1 s of CPU on a 2-core machine)
    raise AssertionError(f"timed out waiting for {what}")


def _actor_version(runs: Path) -> int:
    doc = _status(runs)
    return max((r["extra"].get("published_version", -1) for r in doc.get("roles", []) if r["kind"] == "actor"), default=-1)


@pytest.mark.timeout(600)
def test_killed_roles_restart_and_versions_stay_monotonic(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    run_dir = runs / "tiny"
    up = subprocess.Popen(
        [sys.executable, "-m", "dvla", "up", "topologies/tiny.yaml", "--runs", str(runs),
         "--base-port", str(free_port_block()), "--max-env-steps", "30000", "--quiet"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        _wait(lambda: _actor_version(runs) >= 3, 240, "the actor's third version", up)
        for victim in ("rollout-node0-0", "actor-node0-0", "replicator-node0-0"):
            old = _state(run_dir)["children"][victim]
            before = _actor_version(runs)
            os.kill(old, signal.SIGKILL)
            _wait(lambda: _state(run_dir).get("children", {}).get(victim, old) != old, 60, f"{victim} restarted", up)
            # the run keeps learning after each fault: the actor publishes past what it had
            _wait(lambda: _actor_version(runs) > before, 120, f"new versions after killing {victim}", up)
        doc = _status(runs)
        assert doc["restarts"]["rollout-node0-0"] >= 1
        assert doc["restarts"]["actor-node0-0"] >= 1
        assert doc["restarts"]["replicator-node0-0"] >= 1
        # the run has gone on past every fault: stop it as a user would (the budget is only a bound)
        down = dvla("down", "tiny", "--runs", str(runs), timeout=120)
        assert down.returncode == 0, down.stdout + down.stderr
        out, _ = up.communicate(timeout=120)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    assert up.returncode == 130, out  # ExitCode.INTERRUPTED: stopped by `dvla down`
    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "interrupted", result
    with open(run_dir / "metrics.csv") as f:
        versions = [int(r["version"]) for r in csv.DictReader(f) if int(r["roles_up"]) > 0 and int(r["version"]) > 0]
    assert versions == sorted(versions), "the actor's published version went backwards"
    with open(run_dir / "evals.csv") as f:
        evals = [int(r["version"]) for r in csv.DictReader(f)]
    assert evals == sorted(evals)
    actor_log = (run_dir / "logs" / "actor-node0-0.log").read_text()
    assert "resumed from checkpoint" in actor_log
    assert pids_of_run(run_dir) == []

"""The learner group and durable runs, end to end: real `dvla up`, real torch.distributed (gloo),
real ManiSkill, real kills.

- two ranks hold the same parameters after every version (their checksums, as status reports them);
- kill -9 of rank 1: the group restarts from its checkpoint, versions keep increasing, and no
  version number ever names two different weights;
- kill -9 of `dvla up`, then `dvla up --resume`: the run continues in the same directory from
  the checkpoint, above every earlier version, with the checkpoint's published weights;
- `--mode sync --seed 7` twice: the same version checksums.
"""

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

from benchmarks.ports import free_port_block

ROOT = Path(__file__).resolve().parents[2]

#: tiny.yaml with two learner ranks at 1:1 (each rank learns from 200 env steps per version)
TWO_RANKS = (ROOT / "topologies/tiny.yaml").read_text().replace("batch_steps: 400", "batch_steps: 200").replace(
    "          - role: actor\n", "          - role: actor\n            count: 2\n") + "learners:\n  ratio: \"1:1\"\n"


def dvla(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dvla", *args], capture_output=True, text=True, cwd=ROOT, timeout=timeout)


def start_up(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dvla", "up", *args, "--quiet"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def ledger(run_dir: Path) -> list[dict]:
    """versions.csv: every version rank 0 published, by every incarnation."""
    names = ["version", "checksum", "encoding", "env_steps", "time", "pid"]
    with open(run_dir / "versions.csv") as f:
        return [dict(zip(names, row)) for row in csv.reader(f) if row]


def incarnations(rows: list[dict]) -> list[list[dict]]:
    out: list[list[dict]] = []
    for r in rows:
        if not out or out[-1][-1]["pid"] != r["pid"]:
            out.append([])
        out[-1].append(r)
    return out


def assert_versions_sound(rows: list[dict]) -> None:
    """Versions strictly increase across incarnations; no number names two checksums."""
    seen: dict[int, str] = {}
    for r in rows:
        v = int(r["version"])
        assert seen.setdefault(v, r["checksum"]) == r["checksum"], f"v{v} published as two different weights"
    numbers = [int(r["version"]) for r in rows]
    assert numbers == sorted(set(numbers)), numbers


def pids_of_run(run_dir: Path) -> list[str]:
    out = subprocess.run(["pgrep", "-f", str(run_dir)], capture_output=True, text=True).stdout.split()
    return [p for p in out if p != str(os.getpid())]


def wait_for(pred, timeout: float, what: str, up: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        if up is not None and up.poll() is not None:
            raise AssertionError(f"dvla up exited ({up.returncode}) before {what}:\n{up.stdout.read() if up.stdout else ''}")
        time.sleep(0.5)
    raise AssertionError(f"timed out waiting for {what}")


def published(run_dir: Path) -> int:
    try:
        rows = ledger(run_dir)
    except OSError:
        return 0
    return max((int(r["version"]) for r in rows), default=0)


@pytest.mark.timeout(300)
def test_two_ranks_hold_identical_parameters_after_every_version(tmp_path: Path) -> None:
    topo = tmp_path / "tiny2.yaml"
    topo.write_text(TWO_RANKS)
    runs = tmp_path / "runs"
    up = dvla("up", str(topo), "--runs", str(runs), "--base-port", str(free_port_block()), "--max-env-steps", "2600", "--quiet")
    assert up.returncode == 0, up.stdout + up.stderr
    run_dir = runs / "tiny"
    s0, s1 = (json.loads((run_dir / "summaries" / f"actor-node0-{i}.json").read_text())["extra"] for i in (0, 1))
    assert (s0["rank"], s1["rank"], s0["world_size"]) == (0, 1, 2)
    common = sorted(set(s0["checksums"]) & set(s1["checksums"]), key=int)
    assert len(common) >= 5, (s0["checksums"], s1["checksums"])
    assert all(s0["checksums"][v] == s1["checksums"][v] for v in common), (s0["checksums"], s1["checksums"])
    # rank 0 published exactly the weights both ranks hold
    by_version = {r["version"]: r["checksum"] for r in ledger(run_dir)}
    assert all(by_version[v] == s0["checksums"][v] for v in common)
    # each rank learned from its own rollout (nearest routing at 1:1)
    assert s0["consumed_chunks"] > 0 and s1["consumed_chunks"] > 0
    result = json.loads((run_dir / "result.json").read_text())
    assert result["accounting"]["unaccounted"] == 0, result["accounting"]
    assert pids_of_run(run_dir) == []


@pytest.mark.timeout(420)
def test_kill_of_rank_1_restarts_the_group_from_its_checkpoint(tmp_path: Path) -> None:
    topo = tmp_path / "tiny2.yaml"
    topo.write_text(TWO_RANKS)
    runs = tmp_path / "runs"
    run_dir = runs / "tiny"
    up = start_up(str(topo), "--runs", str(runs), "--base-port", str(free_port_block()), "--max-env-steps", "4800")
    try:
        wait_for(lambda: published(run_dir) >= 5, 240, "version 5 (past the checkpoint at 4)", up)
        before = published(run_dir)
        pid = json.loads((run_dir / "state.json").read_text())["children"]["actor-node0-1"]
        os.kill(pid, signal.SIGKILL)
        up.wait(timeout=300)
    finally:
        if up.poll() is None:
            up.kill()
    out = up.stdout.read() if up.stdout else ""
    assert up.returncode == 0, out
    assert "learner group restarts" in out, out
    rows = ledger(run_dir)
    assert_versions_sound(rows)
    parts = incarnations(rows)
    assert len(parts) == 2, [(p[0]["version"], p[-1]["version"]) for p in parts]
    assert int(parts[1][0]["version"]) > before  # numbering continued above everything published
    resumed = json.loads((run_dir / "summaries" / "actor-node0-0.json").read_text())["extra"]["resumed_from"]
    assert resumed["version"] >= 4  # tiny.yaml checkpoints every other version
    # the restarted group started from the checkpoint: its weights are the ones published then
    assert {r["version"]: r["checksum"] for r in parts[0]}[str(resumed["version"])] == resumed["checksum"]
    assert parts[1][0]["checksum"] == resumed["checksum"]
    result = json.loads((run_dir / "result.json").read_text())
    assert result["restarts"]["actor-node0-1"] >= 1 and result["restarts"]["actor-node0-0"] >= 1
    acct = result["accounting"]
    assert acct["unaccounted"] == 0 and acct["lost_within_bounds"], acct
    assert pids_of_run(run_dir) == []


@pytest.mark.timeout(420)
def test_kill_of_dvla_up_then_resume_continues_the_run(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    run_dir = runs / "tiny"
    port = str(free_port_block())
    up = start_up("topologies/tiny.yaml", "--runs", str(runs), "--base-port", port, "--max-env-steps", "200000")
    try:
        wait_for(lambda: published(run_dir) >= 5, 240, "version 5 (past the checkpoint at 4)", up)
    finally:
        up.kill()  # SIGKILL: the roles die with it (PR_SET_PDEATHSIG), nothing stops cleanly
        up.wait()
    wait_for(lambda: not pids_of_run(run_dir), 30, "the roles to die with dvla up")
    manifest = json.loads((run_dir / "checkpoints" / "MANIFEST.json").read_text())
    before = ledger(run_dir)
    metrics_rows = len((run_dir / "metrics.csv").read_text().splitlines())
    budget = manifest["env_steps"] + 1200
    res = dvla("up", "topologies/tiny.yaml", "--runs", str(runs), "--base-port", port, "--resume",
               "--max-env-steps", str(budget), "--quiet")
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"continuing {run_dir.resolve()}: checkpoint v{manifest['version']}" in res.stderr
    rows = ledger(run_dir)
    assert_versions_sound(rows)
    new = rows[len(before):]
    assert int(new[0]["version"]) > max(int(r["version"]) for r in before)
    published_then = {r["version"]: r["checksum"] for r in before}[str(manifest["version"])]
    assert manifest["checksum"] == published_then == new[0]["checksum"]
    actor = json.loads((run_dir / "summaries" / "actor-node0-0.json").read_text())
    assert actor["extra"]["resumed_from"] == {"version": manifest["version"], "checksum": manifest["checksum"]}
    assert actor["env_steps"] >= budget  # the step count continued from the checkpoint's
    assert len((run_dir / "metrics.csv").read_text().splitlines()) > metrics_rows  # appended, not replaced
    result = json.loads((run_dir / "result.json").read_text())
    assert result["accounting"]["incarnations"]["actor"] == 2 and result["accounting"]["lost_within_bounds"]
    assert pids_of_run(run_dir) == []


@pytest.mark.timeout(300)
def test_sync_mode_with_one_seed_publishes_the_same_versions(tmp_path: Path) -> None:
    checksums = []
    for attempt in range(2):
        runs = tmp_path / f"runs{attempt}"
        res = dvla("up", "topologies/tiny.yaml", "--runs", str(runs), "--base-port", str(free_port_block()),
                   "--mode", "sync", "--seed", "7", "--max-env-steps", "2400", "--quiet")
        assert res.returncode == 0, res.stdout + res.stderr
        checksums.append([r["checksum"] for r in ledger(runs / "tiny")][:5])
    assert len(checksums[0]) == 5 and checksums[0] == checksums[1], checksums

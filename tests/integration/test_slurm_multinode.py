"""`sbatch -N 3 scripts/slurm/dvla.sbatch` on a real three-node Slurm cluster.

As root, the test builds a cluster on this machine (tests/integration/multinode_slurm.py):
slurmctld in the root network namespace, three slurmd's each in a network namespace of its own
(its own address on a bridge and its own hostname), one munged, a switch tree of two leaf
switches (node 0 under leaf0, nodes 1 and 2 under leaf1). No sshd anywhere: every role starts as
a job step.

Job 1 runs the generated topology (tiny.yaml's task, a small budget) to its end: every role is
seen as a step of the job on its node (`squeue -s`), the generated racks are the two leaf
switches and the weight tree enters leaf1 once, the run ends by itself with result.json and its
accounting closes exactly. Job 2 runs a topology file with rank 0 on a node other than the head
and a large budget: one rollout's step is cancelled (`scancel JOB.STEP`) and comes back as a new
step, then `scancel --signal=TERM --batch` stops the run in order (result.json, reason
interrupted, accounting closed exactly) and rank 0's checkpoint is back in the run directory.
Afterwards nothing is left: daemons, namespaces, bridge, processes, files.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from .multinode_slurm import FINAL_STATES, MultiNodeSlurm, missing_tools, tail, tool
from .test_up_e2e import free_port_block

ROOT = Path(__file__).resolve().parents[2]
SBATCH_SCRIPT = "scripts/slurm/dvla.sbatch"
#: processes of Slurm and munge the cluster starts
SLURM_PROCESSES = ("munged", "slurmctld", "slurmd", "slurmstepd")
#: tiny.yaml's batches are 400 env steps: several weight versions
MAX_ENV_STEPS = 1600


def _usable() -> tuple[bool, str]:
    if os.geteuid() != 0:
        return False, "needs root (network namespaces, munged, slurmctld, slurmd)"
    missing = missing_tools()
    if missing:
        return False, (f"needs {', '.join(missing)} (Debian slurm-wlm, munge, util-linux, iproute2; "
                       "bash scripts/setup.sh slurm installs the first two)")
    return True, ""


_OK, _WHY = _usable()
pytestmark = [pytest.mark.slurm, pytest.mark.netns, pytest.mark.slow, pytest.mark.skipif(not _OK, reason=_WHY)]


def _pgrep(pattern: str, *, exact: bool = False) -> set[str]:
    out = subprocess.run(["pgrep", "-x" if exact else "-f", pattern], capture_output=True, text=True).stdout.split()
    return {p for p in out if p != str(os.getpid())}


def _submit(cluster: MultiNodeSlurm, out_dir: Path, env: dict[str, str], *topology: str) -> str:
    """sbatch the script as docs/slurm.md has it (three nodes, this machine's CPUs each); its job id."""
    sub = subprocess.run([tool("sbatch"), "--parsable", "-N", "3", "--ntasks-per-node=1", "-c", str(cluster.cpus),
                          f"--output={out_dir}/dvla-%j.out", SBATCH_SCRIPT, *topology],
                         capture_output=True, text=True, cwd=ROOT, env=cluster.env(**env), timeout=30)
    assert sub.returncode == 0, sub.stderr
    return sub.stdout.strip().split(";")[0]


def _watch_steps(cluster: MultiNodeSlurm, job_id: str, seen: dict[str, set[str]]) -> list[dict[str, str]]:
    """The job's running steps now; adds each step name's node to `seen`."""
    steps = cluster.steps(job_id)
    for s in steps:
        seen.setdefault(s["name"], set()).add(s["nodes"])
    return steps


@pytest.mark.timeout(420)
def test_multinode_sbatch_roles_as_steps_racks_from_switches(tmp_path: Path) -> None:
    daemons_before = {d: _pgrep(d, exact=True) for d in SLURM_PROCESSES}
    started = time.monotonic()
    cluster = MultiNodeSlurm(3, switches=((0,), (1, 2)))
    runs = tmp_path / "runs"
    n0, n1, n2 = cluster.nodes
    try:
        cluster.start()
        cluster_up_s = time.monotonic() - started
        env = {"DVLA_PYTHON": sys.executable, "DVLA_RUNS": str(runs), "DVLA_TASK_FILE": str(ROOT / "topologies/tiny.yaml"),
               "DVLA_ROLLOUTS_PER_NODE": "1", "DVLA_REMOTE_WORKDIR": str(cluster.root / "work")}

        # -- job 1: to its budget ------------------------------------------------------------
        job1 = _submit(cluster, tmp_path, {**env, "DVLA_RUN": "mn", "DVLA_MAX_ENV_STEPS": str(MAX_ENV_STEPS),
                                           "DVLA_BASE_PORT": str(free_port_block())})
        output1 = tmp_path / f"dvla-{job1}.out"
        seen: dict[str, set[str]] = {}
        deadline = time.monotonic() + 200
        while (job := cluster.job(job1)).get("JobState") not in FINAL_STATES:
            assert time.monotonic() < deadline, f"job {job1} still {job.get('JobState')}\n{tail(output1, 40)}"
            _watch_steps(cluster, job1, seen)
            time.sleep(0.5)
        job1_s = time.monotonic() - started - cluster_up_s
        text = output1.read_text(errors="replace")
        assert (job["JobState"], job["ExitCode"]) == ("COMPLETED", "0:0"), f"{job}\n{text}\n{cluster.logs()}"
        run_dir = runs / "mn"
        # every role was a step of the job, on its node (n0 = the first host, and so on)
        roles = {p.stem for p in (run_dir / "roles").glob("*.json")}
        host_of = {"n0": n0, "n1": n1, "n2": n2}
        assert roles == {"actor-n0-0", "replicator-n0-0", "evaluator-n0-0", "replicator-n1-0", "rollout-n1-0",
                         "replicator-n2-0", "rollout-n2-0"}, roles
        assert {r: seen.get(r) for r in roles} == {r: {host_of[r.split("-")[1]]} for r in roles}, seen
        assert "roles start as steps of Slurm job" in text, text
        # racks are the leaf switches; the weight tree enters leaf1 once
        rack = {r: json.loads((run_dir / "roles" / f"{r}.json").read_text())["rack"] for r in roles}
        parent = {r: json.loads((run_dir / "roles" / f"{r}.json").read_text())["parent"] for r in roles}
        assert rack["actor-n0-0"] == "leaf0" and rack["rollout-n1-0"] == rack["rollout-n2-0"] == "leaf1", rack
        assert parent["replicator-n1-0"] == "replicator-n0-0" and parent["replicator-n2-0"] == "replicator-n1-0", parent
        result = json.loads((run_dir / "result.json").read_text())
        assert result["reason"] == "max_env_steps" and result["final_env_steps"] >= MAX_ENV_STEPS, result
        assert result["final_version"] >= 2, result
        assert result["accounting"]["unaccounted"] == 0 and result["accounting"]["consumed"] > 0, result["accounting"]
        # the remote rollouts' summaries came back from their nodes' workdirs
        assert (run_dir / "summaries" / "rollout-n2-0.json").exists(), sorted(os.listdir(run_dir))

        # -- job 2: rank 0 on a remote node; one step cancelled and restarted; then
        #    scancel --signal=TERM --batch; the checkpoint comes back to the run directory ---------
        task = {**yaml.safe_load((ROOT / "topologies/tiny.yaml").read_text())["task"], "budget": {"max_env_steps": 10 ** 7}}
        work = cluster.root / "work"

        def node(i: int, roles: str) -> str:
            return f"      - {{name: n{i}, host: {cluster.nodes[i]}, address: {cluster.addresses[cluster.nodes[i]]}, roles: {roles}}}"

        topo2 = tmp_path / "mn2.yaml"
        topo2.write_text("\n".join([
            "run: mn2", f"base_port: {free_port_block()}", f"task: {json.dumps(task)}",
            f"ssh: {{python: {sys.executable}, workdir: {work}}}", "racks:", "  - name: leaf0", "    nodes:",
            node(0, "[{role: replicator}, {role: evaluator}]"), "  - name: leaf1", "    nodes:",
            node(1, "[{role: actor}, {role: replicator}, {role: rollout}]"),
            node(2, "[{role: replicator}, {role: rollout}]"), ""]))
        job2 = _submit(cluster, tmp_path, env, str(topo2))
        output2, run2 = tmp_path / f"dvla-{job2}.out", runs / "mn2"
        deadline = time.monotonic() + 200

        def wait_for(what: str, ready) -> None:
            while not ready():
                state = cluster.job(job2).get("JobState")
                assert state not in FINAL_STATES, f"job {job2} ended ({state}) before {what}\n{tail(output2, 40)}"
                assert time.monotonic() < deadline, f"{what} never happened\n{tail(output2, 40)}"
                time.sleep(0.5)

        def versions() -> int:  # the actor's, in its node's working directory
            path = work / "mn2" / "versions.csv"
            return len(path.read_text().splitlines()) if path.exists() else 0

        def step_of(name: str) -> dict[str, str] | None:
            return next((s for s in cluster.steps(job2) if s["name"] == name), None)

        # versions.csv's first line is the initial weights (v0): wait for one learned from chunks
        wait_for("a learned weight version with rollout-n2-0 up", lambda: versions() >= 2 and step_of("rollout-n2-0"))
        victim = step_of("rollout-n2-0")
        assert victim is not None and victim["nodes"] == n2, victim
        assert step_of("actor-n1-0")["nodes"] == n1
        assert cluster.run("scancel", victim["id"]).returncode == 0
        wait_for("the cancelled rollout's new step", lambda: any(
            s["name"] == "rollout-n2-0" and s["id"] != victim["id"] for s in cluster.steps(job2)))
        v = versions()
        wait_for("a weight version after the restart", lambda: versions() > v)
        assert cluster.run("scancel", "--signal=TERM", "--batch", job2).returncode == 0
        while (job := cluster.job(job2)).get("JobState") not in FINAL_STATES:
            assert time.monotonic() < deadline + 60, f"job {job2} did not stop after SIGTERM\n{tail(output2, 40)}"
            time.sleep(0.5)
        text2 = output2.read_text(errors="replace")
        result2 = json.loads((run2 / "result.json").read_text())
        assert result2["reason"] == "interrupted" and result2["restarts"]["rollout-n2-0"] == 1, result2
        assert result2["accounting"]["unaccounted"] == 0, result2["accounting"]
        assert job["ExitCode"] == "130:0", f"{job}\n{text2}"  # dvla up's code for an interrupted run
        assert cluster.steps(job2) == []
        # the remote rank 0's checkpoint came back: --resume on any node continues from it
        manifest = json.loads((run2 / "checkpoints" / "MANIFEST.json").read_text())
        assert manifest == json.loads((work / "mn2" / "checkpoints" / "MANIFEST.json").read_text())
        assert (run2 / "checkpoints" / manifest["dir"] / "policy.safetensors").exists()
        for log in [*(runs / "mn" / "logs").glob("*.log"), *(run2 / "logs").glob("*.log")]:
            assert "Fatal Python error" not in log.read_text(errors="replace"), tail(log)
    finally:
        cluster.stop()
    print(f"three-node Slurm: cluster up in {cluster_up_s:.1f} s, job 1 {job1_s:.1f} s, "
          f"{time.monotonic() - started:.1f} s in all")
    deadline = time.monotonic() + 10
    while (left_over := cluster.leftovers()) and time.monotonic() < deadline:
        time.sleep(0.5)  # a namespace's last process may take a moment to be reaped
    assert left_over == []
    assert _pgrep(str(cluster.root)) == set() and _pgrep(str(runs)) == set()
    deadline = time.monotonic() + 10
    while (left := {d: _pgrep(d, exact=True) - daemons_before[d] for d in SLURM_PROCESSES}) and any(left.values()):
        assert time.monotonic() < deadline, f"left running: {left}"
        time.sleep(0.5)

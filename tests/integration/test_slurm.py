"""`sbatch scripts/slurm/dvla.sbatch` on a real single-host Slurm cluster.

As root, the test builds a cluster of this machine alone: a fresh munge key and a munged on its
own socket, a minimal slurm.conf (one node described by `slurmd -C`, one partition, no
accounting, no cgroups), slurmctld and slurmd in the foreground, everything under one temporary
directory on ports of their own; no Slurm or munge file of the system is read or written. It then submits the batch
script as docs/slurm.md tells users to, with the tiny topology as its argument, so the script's
whole path runs for real: `scontrol show hostnames`, `dvla plan`, the `dvla doctor` preflight as
an `srun` step, and `dvla up` as the batch step, which starts every role as a step of the job. While the job runs, `dvla status` (from outside
the job) reaches the run and names every role; once it ends: the job completed with exit code
0:0, the run reached its step budget with a final weight version, `dvla logs` reads a role's
log, and the job's output file carries each stage. Afterwards the daemons are stopped and nothing
of the cluster or the run is left (processes or files), whether the test passed or not.

Without root, with `scontrol` alone, the script's dry run is checked: host lists expand outside
a cluster, and a host that does not resolve is left without an address there but stops a job.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .multinode_slurm import FINAL_STATES, SEARCH_PATH, SlurmDaemons, client_env, tail, tool
from .test_up_e2e import ROLES, check_status_schema, free_port_block

ROOT = Path(__file__).resolve().parents[2]
SBATCH_SCRIPT = "scripts/slurm/dvla.sbatch"
#: the daemons and clients the test runs (Debian: slurm-wlm and munge)
TOOLS = ("munged", "slurmctld", "slurmd", "sbatch", "srun", "scontrol", "sinfo", "scancel")
#: process names of Slurm and munge (slurmctld's helper slurmscriptd goes by its name too)
SLURM_PROCESSES = ("munged", "slurmctld", "slurmd", "slurmstepd")
#: small enough to end quickly, large enough for several weight versions (tiny.yaml: 400 steps each)
MAX_ENV_STEPS = 1600


def _usable() -> tuple[bool, str]:
    if os.geteuid() != 0:
        return False, "needs root (starts munged, slurmctld and slurmd)"
    missing = [t for t in TOOLS if shutil.which(t, path=SEARCH_PATH) is None]
    if missing:
        return False, (f"needs {', '.join(missing)} "
                       "(Debian slurm-wlm and munge; bash scripts/setup.sh slurm installs them)")
    return True, ""


_OK, _WHY = _usable()
pytestmark = pytest.mark.slurm
needs_cluster = pytest.mark.skipif(not _OK, reason=_WHY)
needs_scontrol = pytest.mark.skipif(
    shutil.which("scontrol") is None,
    reason="needs scontrol (Debian slurm-client; bash scripts/setup.sh slurm installs it)")
#: a host list of made-up names (a run with remote nodes may not use loopback addresses)
DRY_RUN_NODES = "dvla-nohost-[1-3]"


class SingleHostSlurm(SlurmDaemons):
    """munged, slurmctld and slurmd for this host alone, all under one temporary directory."""

    def __init__(self) -> None:
        # `slurmd -C`: this host as slurmd will describe itself ("NodeName=vm CPUs=2 ...").
        node_line = subprocess.run([tool("slurmd"), "-C"], capture_output=True, text=True, check=True,
                                   timeout=30).stdout.splitlines()[0]
        fields = dict(f.split("=", 1) for f in node_line.split())
        self.node, self.cpus, self.node_line = fields["NodeName"], int(fields["CPUs"]), node_line
        super().__init__("dvla-slurm-")

    def start(self) -> None:
        self._start_munge()
        ctld_port = free_port_block(2)
        for d in ("state", "spool"):
            (self.root / d).mkdir(mode=0o700)
        (self.root / "plugstack.conf").write_text("")  # not the system's /etc/slurm/plugstack.conf
        r = self.root
        self.conf.write_text("\n".join([
            "ClusterName=dvlatest",
            f"SlurmctldHost={self.node}",
            "SlurmUser=root",
            "SlurmdUser=root",
            f"SlurmctldPort={ctld_port}",
            f"SlurmdPort={ctld_port + 1}",
            "AuthType=auth/munge",
            "CredType=cred/munge",
            f"AuthInfo=socket={self.socket}",
            f"StateSaveLocation={r}/state",
            f"SlurmdSpoolDir={r}/spool",
            f"SlurmctldPidFile={r}/slurmctld.pid",
            f"SlurmdPidFile={r}/slurmd.pid",
            f"SlurmctldLogFile={r}/slurmctld.log",
            f"SlurmdLogFile={r}/slurmd.log",
            f"PlugStackConfig={r}/plugstack.conf",
            # processes tracked by parentage and no task binding: no cgroups needed
            "ProctrackType=proctrack/linuxproc",
            "TaskPlugin=task/none",
            "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_Core",
            "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none",
            "JobCompType=jobcomp/none",
            "MpiDefault=none",
            "ReturnToService=2",
            f"{self.node_line} State=UNKNOWN",
            f"PartitionName=dvla Nodes={self.node} Default=YES MaxTime=INFINITE State=UP",
            "",
        ]))
        for name in ("slurmctld", "slurmd"):
            self._spawn(name, [tool(name), "-D", "-f", str(self.conf)])
        self._wait(lambda: self.run("sinfo", "-h", "-n", self.node, "-o", "%T").stdout.strip() == "idle",
                   30, "node never became idle in sinfo")

    def stop(self) -> None:
        """Cancel what still runs, stop the daemons (newest first) and remove the directory."""
        if "slurmctld" in self.daemons and self.daemons["slurmctld"].poll() is None:
            live = [j["JobId"] for j in self.jobs() if j.get("JobState") not in FINAL_STATES]
            if live:
                self.run("scancel", *live)
                try:
                    self._wait(lambda: all(self.job(j).get("JobState") in FINAL_STATES for j in live), 30,
                               "jobs did not end after scancel")
                except RuntimeError:
                    pass
        for name, proc in reversed(self.daemons.items()):
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        shutil.rmtree(self.root, ignore_errors=True)


def _pgrep(pattern: str, *, exact: bool = False) -> list[str]:
    out = subprocess.run(["pgrep", "-x" if exact else "-f", pattern], capture_output=True, text=True).stdout.split()
    return [p for p in out if p != str(os.getpid())]


def _wait_gone(before: dict[str, set[str]], timeout: float = 10) -> dict[str, set[str]]:
    """Slurm and munge processes that are not in `before` and still there after `timeout` (a
    slurmstepd just ended may linger a moment as a zombie, until init reaps it)."""
    deadline = time.monotonic() + timeout
    while True:
        left = {d: set(_pgrep(d, exact=True)) - before[d] for d in SLURM_PROCESSES}
        left = {d: pids for d, pids in left.items() if pids}
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.5)


def dvla(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dvla", *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=timeout)


@needs_scontrol
def test_dry_run_expands_hosts_outside_a_cluster(tmp_path: Path) -> None:
    # no SLURM_CONF: scontrol without a cluster's configuration, as on a workstation
    env = client_env(DVLA_DRY_RUN="1", SLURM_JOB_NODELIST=DRY_RUN_NODES, DVLA_PYTHON=sys.executable,
                      DVLA_RUNS=str(tmp_path))
    dry = subprocess.run(["bash", SBATCH_SCRIPT], capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    assert dry.returncode == 0, dry.stdout + dry.stderr
    topo = (tmp_path / "slurm-manual.topology.yaml").read_text()
    for host in ("dvla-nohost-1", "dvla-nohost-2", "dvla-nohost-3"):
        assert f"host: {host}\n        roles:" in topo, topo  # no address line
        assert f"dvla slurm: {host} does not resolve here" in dry.stderr, dry.stderr


@needs_scontrol
def test_job_stops_on_a_host_that_does_not_resolve(tmp_path: Path) -> None:
    conf = tmp_path / "slurm.conf"  # enough for scontrol to expand host lists
    conf.write_text("ClusterName=dvlatest\nSlurmctldHost=localhost\n")
    runs = tmp_path / "runs"
    env = client_env(SLURM_CONF=str(conf), SLURM_JOB_NODELIST=DRY_RUN_NODES, DVLA_PYTHON=sys.executable,
                      DVLA_RUNS=str(runs))
    job = subprocess.run(["bash", SBATCH_SCRIPT], capture_output=True, text=True, cwd=ROOT, env=env, timeout=60)
    assert job.returncode == 2 and "cannot resolve dvla-nohost-1" in job.stderr, job.stdout + job.stderr
    assert list(runs.iterdir()) == []  # no topology written, nothing started
    one = subprocess.run(["bash", SBATCH_SCRIPT], capture_output=True, text=True, cwd=ROOT, timeout=60,
                         env={**env, "SLURM_JOB_NODELIST": "dvla-nohost-1"})
    assert one.returncode == 2 and "needs at least 2 nodes" in one.stderr, one.stderr


@needs_cluster
@pytest.mark.timeout(360)
def test_sbatch_tiny_on_single_host_slurm(tmp_path: Path) -> None:
    # tiny.yaml on ports of its own (tests and runs may share this machine)
    topo = tmp_path / "tiny.yaml"
    topo.write_text((ROOT / "topologies" / "tiny.yaml").read_text() + f"\nbase_port: {free_port_block()}\n")
    runs, run_dir = tmp_path / "runs", tmp_path / "runs" / "tiny"
    daemons_before = {d: set(_pgrep(d, exact=True)) for d in SLURM_PROCESSES}
    started = time.monotonic()
    cluster = SingleHostSlurm()
    try:
        cluster.start()
        cluster_up_s = time.monotonic() - started
        env = {**cluster.env(), "DVLA_PYTHON": sys.executable, "DVLA_RUNS": str(runs),
               "DVLA_MAX_ENV_STEPS": str(MAX_ENV_STEPS)}
        # As docs/slurm.md has it, from the checkout; -N and -c fit the allocation to this one host.
        sub = subprocess.run([tool("sbatch"), "--parsable", "-N", "1", "-c", str(cluster.cpus),
                              f"--output={tmp_path}/dvla-%j.out", SBATCH_SCRIPT, str(topo)],
                             capture_output=True, text=True, cwd=ROOT, env=env, timeout=30)
        assert sub.returncode == 0, sub.stderr
        job_id = sub.stdout.strip().split(";")[0]
        output = tmp_path / f"dvla-{job_id}.out"

        # `dvla status` from outside the job, until the actor answers with a weight version; the
        # document (in docs/status.md's schema) names every role of the run, answering or silent.
        # (That every role answers is test_up_e2e's: on a loaded machine the rollouts and the
        # evaluator miss many reply windows.) Asking stops there: a call that starts as the run
        # ends waits out its session-open timeout.
        status_doc: dict | None = None
        last_status = "(never asked: no state.json while the job ran)"
        deadline = time.monotonic() + 240
        while (job := cluster.job(job_id)).get("JobState") not in FINAL_STATES:
            assert time.monotonic() < deadline, f"job {job_id} still {job.get('JobState')}\n{tail(output, 40)}"
            if status_doc is None and (run_dir / "state.json").exists():
                try:
                    st = dvla("status", "tiny", "--runs", str(runs), "--format", "json", "--timeout", "5", timeout=40)
                except subprocess.TimeoutExpired:
                    last_status = "no answer in 40 s"
                    continue
                last_status = f"rc {st.returncode}: {st.stdout[-2000:]}{st.stderr[-2000:]}"
                if st.returncode == 0:
                    doc = json.loads(st.stdout)
                    check_status_schema(doc)
                    actor = [r for r in doc["roles"] if r["name"] == "actor-node0-0"]
                    if actor and actor[0]["policy_version"] >= 1:
                        status_doc = doc
            time.sleep(1)
        job_s = time.monotonic() - started - cluster_up_s
        text = output.read_text(errors="replace")
        assert (job["JobState"], job["ExitCode"]) == ("COMPLETED", "0:0"), f"{job}\n{text}"
        assert status_doc is not None, f"dvla status never had the actor's version; last: {last_status}\n{text}"
        assert {r["name"] for r in status_doc["roles"]} | set(status_doc["silent"]) == ROLES, status_doc

        result = json.loads((run_dir / "result.json").read_text())
        assert result["reason"] == "max_env_steps" and result["final_env_steps"] >= MAX_ENV_STEPS, result
        assert result["final_version"] >= 2, result
        logs = dvla("logs", "actor-node0-0", "--run", "tiny", "--runs", str(runs), "-n", "5")
        assert logs.returncode == 0 and "actor-node0-0" in logs.stdout, logs.stdout + logs.stderr

        # every stage of the script, in order, in the job's output file
        stages = [f"dvla.sbatch: 1 nodes ({cluster.node}); topology {topo}",  # scontrol show hostnames
                  "weight tree:",  # dvla plan
                  "this host can run its roles",  # dvla doctor, as an srun step
                  f"dvla: run tiny -> {run_dir}",  # dvla up, the batch step
                  "dvla: run tiny ended: max_env_steps"]
        assert f"roles start as steps of Slurm job {job_id}" in text, text  # launcher: auto, inside a job
        positions = [text.find(s) for s in stages]
        assert -1 not in positions and positions == sorted(positions), f"{list(zip(stages, positions))}\n{text}"
    finally:
        cluster.stop()
    print(f"single-host Slurm: cluster up in {cluster_up_s:.1f} s, job {job_s:.1f} s, "
          f"{time.monotonic() - started:.1f} s in all")
    assert all(p.returncode is not None for p in cluster.daemons.values())
    assert not cluster.root.exists()
    assert _pgrep(str(cluster.root)) == [] and _pgrep(str(run_dir)) == []
    left = _wait_gone(daemons_before)
    assert not left, f"left running: {left}"

"""Slurm: reading an allocation (host lists, switch tree, CPUs, GPUs, addresses) from the text
Slurm prints, the topology generated from it, choosing the launcher, and role steps' command
lines (never a secret on them)."""

from __future__ import annotations

import json
import sys

import pytest

from dvla.config import RoleConfig
from dvla.orchestrator.plan import make_plan
from dvla.orchestrator.process import Process
from dvla.orchestrator.slurm import (GenerateSettings, SlurmError, SlurmJob, SlurmWrapper, expand_hostlist,
                                     generate_topology, parse_cpus_per_node, parse_hostnames, parse_job_gpus,
                                     parse_switch_tree, slurm_job_for)
from dvla.orchestrator.topology import parse_topology

#: `scontrol show hostnames 'gpu-[002-004],login1,rack[1-2]-n[08-10],a[9-11]'` (Slurm 22.05.8)
HOSTNAMES_LIST = "gpu-[002-004],login1,rack[1-2]-n[08-10],a[9-11]"
HOSTNAMES_OUT = """gpu-002
gpu-003
gpu-004
login1
rack1-n08
rack1-n09
rack1-n10
rack2-n08
rack2-n09
rack2-n10
a9
a10
a11
"""

#: `scontrol show topology` of a three-node cluster with two leaf switches (Slurm 22.05.8)
TOPOLOGY_OUT = """SwitchName=leaf0 Level=0 LinkSpeed=1 Nodes=dnb9850
SwitchName=leaf1 Level=0 LinkSpeed=1 Nodes=dnb9851,dnb9852
SwitchName=top Level=1 LinkSpeed=1 Nodes=dnb[9850-9852] Switches=leaf0,leaf1
"""

#: `scontrol show job -d` of a two-node GPU job (per-node lines as Slurm 22.05 prints them)
JOB_DETAIL_OUT = """JobId=41 JobName=dvla
   UserId=u(1000) GroupId=u(1000) MCS_label=N/A
   NodeList=gpu-[001-002]
   TRES=cpu=16,mem=64G,node=2,billing=16,gres/gpu=6
     Nodes=gpu-001 CPU_IDs=0-7 Mem=32768 GRES=gpu:a100:4(IDX:0-3)
     Nodes=gpu-002 CPU_IDs=0-7 Mem=32768 GRES=gpu:2(IDX:0-1)
"""

NODE_OUT = """NodeName=dnb9850 Arch=x86_64 CoresPerSocket=1 CPUAlloc=0 NodeAddr=10.79.3.10 NodeHostName=dnb9850 Version=22.05.8
NodeName=dnb9851 Arch=x86_64 CoresPerSocket=1 CPUAlloc=0 NodeAddr=10.79.3.11 NodeHostName=dnb9851 Version=22.05.8
NodeName=dnb9852 Arch=x86_64 CoresPerSocket=1 CPUAlloc=0 NodeAddr=10.79.3.12 NodeHostName=dnb9852 Version=22.05.8
"""

JOB_ENV = {"SLURM_JOB_ID": "77", "SLURM_JOB_NODELIST": "dnb[9850-9852]", "SLURMD_NODENAME": "dnb9850",
           "SLURM_JOB_CPUS_PER_NODE": "2(x3)"}


def fake_scontrol(topology: str = TOPOLOGY_OUT, job: str = "", nodes: str = NODE_OUT):
    def run(*args: str) -> str:
        return {"topology": topology, "job": job, "node": nodes}[args[1]]
    return run


def test_host_lists_expand_as_scontrol_show_hostnames_does() -> None:
    assert expand_hostlist(HOSTNAMES_LIST) == parse_hostnames(HOSTNAMES_OUT)
    assert expand_hostlist("n1") == ["n1"]
    for bad in ("n[1-", "n]1[", "n[3-1]", "n[a-b]"):
        with pytest.raises(ValueError):
            expand_hostlist(bad)


def test_switch_tree_gives_the_leaf_switches_and_their_hosts() -> None:
    assert parse_switch_tree(TOPOLOGY_OUT) == {"leaf0": ["dnb9850"], "leaf1": ["dnb9851", "dnb9852"]}
    assert parse_switch_tree("") == {}  # topology/none prints nothing


def test_cpus_and_gpus_per_node() -> None:
    assert parse_cpus_per_node("8(x2),4", ["a", "b", "c"]) == {"a": 8, "b": 8, "c": 4}
    with pytest.raises(ValueError, match="lists 2 node"):
        parse_cpus_per_node("8(x2)", ["a", "b", "c"])
    assert parse_job_gpus(JOB_DETAIL_OUT) == {"gpu-001": 4, "gpu-002": 2}


def test_job_racks_follow_the_leaf_switches() -> None:
    job = SlurmJob.from_env(JOB_ENV, fake_scontrol())
    assert job.hosts == ("dnb9850", "dnb9851", "dnb9852") and job.this_host == "dnb9850"
    assert job.cpus == {"dnb9850": 2, "dnb9851": 2, "dnb9852": 2}
    assert job.addresses["dnb9851"] == "10.79.3.11"
    assert job.racks() == [("leaf0", ["dnb9850"]), ("leaf1", ["dnb9851", "dnb9852"])]
    flat = SlurmJob.from_env(JOB_ENV, fake_scontrol(topology=""))
    assert flat.racks() == [("job77", ["dnb9850", "dnb9851", "dnb9852"])]


def _generated(job: SlurmJob, **kw) -> str:
    text, notes = generate_topology(job, GenerateSettings(run="s77", python=sys.executable, **kw))
    assert notes == []
    return text


def test_generated_topology_takes_a_task_section() -> None:
    job = SlurmJob.from_env(JOB_ENV, fake_scontrol())
    text = _generated(job, task={"env": "PushCube-v1", "ppo": {"batch_steps": 400}, "budget": {"max_wall_s": 60}},
                      max_env_steps=1200)
    task = parse_topology(text, "gen.yaml").task
    assert task.ppo.batch_steps == 400 and task.budget.max_env_steps == 1200 and task.budget.max_wall_s == 60


def test_generated_topology_plans_one_rack_per_leaf_switch() -> None:
    topo = parse_topology(_generated(SlurmJob.from_env(JOB_ENV, fake_scontrol())), "gen.yaml")
    assert [(r.name, [n.host for n in r.nodes]) for r in topo.racks] == [
        ("leaf0", ["dnb9850"]), ("leaf1", ["dnb9851", "dnb9852"])]
    plan = make_plan(topo, "/tmp/run")
    rack = {p.config.name: p.config.rack for p in plan.processes}
    # the weight tree enters rack leaf1 once (at n1's replicator), n2's replicator hangs below it
    assert plan.by_name("replicator-n1-0").config.parent == "replicator-n0-0"
    assert plan.by_name("replicator-n2-0").config.parent == "replicator-n1-0"
    assert rack["rollout-n2-0"] == rack["replicator-n1-0"] == "leaf1" and rack["actor-n0-0"] == "leaf0"
    flat = parse_topology(_generated(SlurmJob.from_env(JOB_ENV, fake_scontrol(topology=""))), "gen.yaml")
    assert [r.name for r in flat.racks] == ["job77"]


def test_generated_topology_places_an_actor_per_gpu_of_the_first_node() -> None:
    job = SlurmJob.from_env({**JOB_ENV, "SLURM_JOB_NODELIST": "gpu-[001-002]", "SLURMD_NODENAME": "gpu-001",
                             "SLURM_JOB_CPUS_PER_NODE": "8(x2)"},
                            fake_scontrol(topology="", job=JOB_DETAIL_OUT, nodes=""))
    assert job.gpus == {"gpu-001": 4, "gpu-002": 2}
    text, notes = generate_topology(job, GenerateSettings(run="g", python="python3", dry_run=True))
    topo = parse_topology(text, "gpu.yaml")
    assert topo.task.device == "cuda" and topo.racks[0].nodes[0].role_counts()["actor"] == 4
    assert notes == [f"{h} does not resolve here: no address for it in this dry run" for h in ("gpu-001", "gpu-002")]
    with pytest.raises(SlurmError, match="cannot resolve gpu-001"):
        generate_topology(job, GenerateSettings(run="g", python="python3"))


TWO_NODES = """
run: t
launcher: {launcher}
racks:
  - name: r
    nodes:
      - {{name: a, host: dnb9850, address: 10.79.3.10, roles: [{{role: actor}}, {{role: replicator}}]}}
      - {{name: b, host: {other}, address: 10.79.3.11, roles: [{{role: rollout}}]}}
"""


def test_launcher_is_chosen_by_the_topology_or_the_enclosing_job(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("dvla.orchestrator.slurm.shutil.which", lambda name: f"/usr/bin/{name}")
    monkeypatch.setattr("dvla.orchestrator.slurm._scontrol", fake_scontrol())
    auto = parse_topology(TWO_NODES.format(launcher="auto", other="dnb9851"))
    assert slurm_job_for(auto, {}) is None  # no job: SSH, as before
    assert slurm_job_for(auto, JOB_ENV).job_id == "77"
    assert slurm_job_for(parse_topology(TWO_NODES.format(launcher="ssh", other="dnb9851")), JOB_ENV) is None
    with pytest.raises(SlurmError, match="launcher: slurm: not inside a Slurm job"):
        slurm_job_for(parse_topology(TWO_NODES.format(launcher="slurm", other="dnb9851")), {})


def _wrapper(tmp_path, other: str = "dnb9851") -> tuple[SlurmWrapper, dict[str, Process]]:
    topo = parse_topology(TWO_NODES.format(launcher="slurm", other=other), "two.yaml")
    job = SlurmJob.from_env(JOB_ENV, fake_scontrol())
    plan = make_plan(topo, str(tmp_path))
    wrapper = SlurmWrapper(topo, "ab" * 32, {"DVLA_SECRET": "ab" * 32, "PATH": "/bin"}, job, tmp_path)
    return wrapper, {p.config.name: p for p in plan.processes}


def test_every_role_is_a_step_on_its_node_with_its_secrets_on_stdin(tmp_path) -> None:
    wrapper, procs = _wrapper(tmp_path)
    wrapper.check_all()
    for name, node in (("actor-a-0", "dnb9850"), ("rollout-b-0", "dnb9851")):
        proc = procs[name]
        role_argv = [sys.executable, "-m", f"dvla.roles.{proc.config.kind}", "--config", "x.json"]
        argv = wrapper(proc, role_argv)
        assert argv[0].endswith("srun") and f"--nodelist={node}" in argv and "--overlap" in argv
        assert "--nodes=1" in argv and "--ntasks=1" in argv and f"--job-name={name}" in argv
        assert "--cpus-per-task=2" in argv and argv[-3:] == ["-m", "dvla.orchestrator.ssh", "serve"]
        env = wrapper.child_env(proc, {"DVLA_SECRET": "ab" * 32, "DVLA_IDENTITY": "who", "PATH": "/bin"})
        assert env == {"PATH": "/bin"}  # srun would export them to the step
        header = json.loads(wrapper.stdin_payload(proc, role_argv, identity="who"))
        assert header["secret"] == "ab" * 32 and header["identity"] == "who"
        assert not any("ab" * 32 in a for a in argv)
        assert RoleConfig.from_json(json.dumps(header["config"])).name == name
        # this host's roles work in the run directory itself; another node's in its workdir
        assert header["in_place"] is (node == "dnb9850")
        assert (header["run_dir"] == str(tmp_path)) is (node == "dnb9850")
        assert (wrapper.output_path(type("S", (), {"proc": proc, "log_path": tmp_path / "logs" / "x.log",
                                                  "name": name})()) is None) is (node == "dnb9850")


def test_a_host_outside_the_job_is_refused_in_one_line(tmp_path) -> None:
    wrapper, _procs = _wrapper(tmp_path, other="elsewhere")
    with pytest.raises(SlurmError, match=r"two.yaml: node b: host 'elsewhere' is not a node of Slurm job 77"):
        wrapper.check_all()


def test_doctor_checks_no_ssh_login_when_roles_start_as_steps(monkeypatch: pytest.MonkeyPatch) -> None:
    from dvla.orchestrator.doctor import Needs, check_ssh

    monkeypatch.setattr("dvla.orchestrator.slurm.shutil.which", lambda name: f"/usr/bin/{name}")
    monkeypatch.setattr("dvla.orchestrator.slurm._scontrol", fake_scontrol())
    for key, value in JOB_ENV.items():
        monkeypatch.setenv(key, value)
    topo = parse_topology(TWO_NODES.format(launcher="auto", other="dnb9851"))
    [result] = check_ssh(topo, Needs(remote_nodes=("b",), topology=True))
    assert "steps of Slurm job 77, not over SSH" in result.detail
    monkeypatch.delenv("SLURM_JOB_ID")
    monkeypatch.delenv("SLURM_JOB_NODELIST")
    [result] = check_ssh(parse_topology(TWO_NODES.format(launcher="slurm", other="dnb9851")),
                         Needs(remote_nodes=("b",), topology=True))
    assert result.status == "fail" and "not inside a Slurm job" in result.detail

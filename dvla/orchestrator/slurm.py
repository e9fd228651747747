"""Slurm: an allocation read as a cluster, and roles started as steps of the job.

Two halves (docs/slurm.md walks both):

- Reading the allocation (:class:`SlurmJob`): its hosts, each node's CPUs, GPUs and address, and
  the switch tree (``scontrol show topology``). The parsers take the text Slurm prints, so they
  are tested on real output; :func:`generate_topology` turns a job into the topology
  scripts/slurm/dvla.sbatch runs, with one rack per leaf switch.
- Launching (:class:`SlurmWrapper`): every role, on every node of the job (this one included), is
  one job step, ``srun --nodes=1 --ntasks=1 --nodelist=NODE --overlap ...``, running the remote
  half of the SSH launcher (``python -m dvla.orchestrator.ssh serve``): the config and secrets go
  on the step's stdin (srun forwards it; never argv or the step's environment), closing it stops
  the role, and the role's result files come back as a tar on the step's stdout. Roles so run in
  the job's cgroup and accounting, receive Slurm's signals and need no SSH.

Run as ``python -m dvla.orchestrator.slurm topology OUT`` inside a job, it writes the generated
topology (settings from ``DVLA_*`` environment variables, see :func:`main`).
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

from ..config import Topology
from .process import CommandWrapper, Process, Supervised, is_local_host
from .ssh import SshTarget, SshWrapper

#: the environment variable whose presence means "inside a Slurm job"
JOB_ENV = "SLURM_JOB_ID"
#: seconds a `scontrol` query may take
SCONTROL_TIMEOUT_S = 30.0


class SlurmError(RuntimeError):
    """The Slurm job cannot run the topology as asked (one line, naming the node or setting)."""


# ----------------------------------------------------------------------------------------------
# Parsing what Slurm prints


_RANGE_RE = re.compile(r"^(\d+)(?:-(\d+))?$")


def expand_hostlist(text: str) -> list[str]:
    """Slurm's compressed host list, expanded in order, as ``scontrol show hostnames`` does:
    ``gpu-[002-004],login1`` -> gpu-002 gpu-003 gpu-004 login1 (zero padding kept; several
    bracket groups in one name multiply out). Raises ValueError on a malformed list."""
    names: list[str] = []
    for item in _split_top_level(text.strip()):
        names.extend(_expand_one(item))
    return names


def _split_top_level(text: str) -> list[str]:
    """Split at commas outside brackets."""
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
            if depth < 0:
                raise ValueError(f"host list {text!r}: ']' without '['")
        elif ch == "," and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    if depth:
        raise ValueError(f"host list {text!r}: '[' without ']'")
    parts.append(text[start:])
    return [p for p in (p.strip() for p in parts) if p]


def _expand_one(item: str) -> list[str]:
    open_at = item.find("[")
    if open_at < 0:
        return [item]
    close_at = item.index("]", open_at)
    prefix, body, rest = item[:open_at], item[open_at + 1:close_at], item[close_at + 1:]
    middles = []
    for rng in body.split(","):
        m = _RANGE_RE.match(rng.strip())
        if m is None:
            raise ValueError(f"host list item {item!r}: bad range {rng!r}")
        lo, hi = m[1], m[2] or m[1]
        if int(hi) < int(lo):
            raise ValueError(f"host list item {item!r}: range {rng!r} runs backwards")
        width = len(lo) if lo.startswith("0") or len(lo) == len(hi) else 0
        middles.extend(str(n).zfill(width) for n in range(int(lo), int(hi) + 1))
    return [prefix + mid + tail for mid in middles for tail in _expand_one(rest)]


def parse_hostnames(text: str) -> list[str]:
    """The output of ``scontrol show hostnames LIST``: one host per line."""
    return [line.strip() for line in text.splitlines() if line.strip()]


def _fields(line: str) -> dict[str, str]:
    """``Key=Value Key2=Value2`` -> dict (values have no spaces in these listings)."""
    return dict(f.split("=", 1) for f in line.split() if "=" in f)


def parse_switch_tree(text: str) -> dict[str, list[str]]:
    """Leaf switches (``Level=0``) of ``scontrol show topology``'s output and the hosts under
    each, in the order printed; {} without a switch tree (``topology/none`` prints nothing)."""
    leaves: dict[str, list[str]] = {}
    for line in text.splitlines():
        f = _fields(line)
        if "SwitchName" in f and f.get("Level") == "0" and f.get("Nodes"):
            leaves[f["SwitchName"]] = expand_hostlist(f["Nodes"])
    return leaves


def parse_cpus_per_node(text: str, hosts: list[str]) -> dict[str, int]:
    """``SLURM_JOB_CPUS_PER_NODE`` (``8(x2),4``: counts in host order, ``(xN)`` repeating one)
    spread over `hosts`; ValueError when it does not cover them."""
    counts: list[int] = []
    for part in _split_top_level(text):
        m = re.fullmatch(r"(\d+)(?:\(x(\d+)\))?", part)
        if m is None:
            raise ValueError(f"SLURM_JOB_CPUS_PER_NODE={text!r}: cannot read {part!r}")
        counts.extend([int(m[1])] * int(m[2] or 1))
    if len(counts) != len(hosts):
        raise ValueError(f"SLURM_JOB_CPUS_PER_NODE={text!r} lists {len(counts)} node(s), the job has {len(hosts)}")
    return dict(zip(hosts, counts))


_GPU_GRES_RE = re.compile(r"(?:^|,)gpu(?::[A-Za-z0-9_.-]+)?:(\d+)")


def parse_job_gpus(text: str) -> dict[str, int]:
    """GPUs per host from ``scontrol show job -d JOB``'s per-node lines (``Nodes=gpu-[1-2]
    CPU_IDs=0-7 Mem=0 GRES=gpu:a100:4(IDX:0-3)``); hosts without GPU GRES are left out."""
    gpus: dict[str, int] = {}
    for line in text.splitlines():
        f = _fields(line)
        if "Nodes" not in f or "CPU_IDs" not in f:
            continue
        n = sum(int(m[1]) for m in _GPU_GRES_RE.finditer(f.get("GRES", "")))
        if n:
            for host in expand_hostlist(f["Nodes"]):
                gpus[host] = n
    return gpus


def parse_node_addresses(text: str) -> dict[str, str]:
    """``NodeName -> NodeAddr`` from ``scontrol show node -o``'s lines."""
    out = {}
    for line in text.splitlines():
        f = _fields(line)
        if "NodeName" in f and f.get("NodeAddr"):
            out[f["NodeName"]] = f["NodeAddr"]
    return out


# ----------------------------------------------------------------------------------------------
# The job


def _scontrol(*args: str) -> str:
    """``scontrol ARGS``' output, or "" when scontrol is missing or fails (outside a cluster)."""
    exe = shutil.which("scontrol")
    if exe is None:
        return ""
    try:
        proc = subprocess.run([exe, *args], capture_output=True, text=True, timeout=SCONTROL_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return proc.stdout if proc.returncode == 0 else ""


def resolve_ipv4(host: str) -> str | None:
    """`host`'s first IPv4 address in the resolver (itself when it is one), or None."""
    try:
        ipaddress.IPv4Address(host)
        return host
    except ValueError:
        pass
    try:
        return socket.getaddrinfo(host, None, socket.AF_INET)[0][4][0]
    except (OSError, IndexError):
        return None


@dataclass(frozen=True)
class SlurmJob:
    """What dvla needs of a Slurm allocation."""

    job_id: str
    #: the allocated hosts, in allocation order
    hosts: tuple[str, ...]
    #: the host this process runs on when it is one of them (SLURMD_NODENAME), else None (a
    #: login node inside `salloc`)
    this_host: str | None = None
    #: CPUs of the job on each host
    cpus: dict[str, int] = field(default_factory=dict)
    #: GPUs of the job on each host that has any
    gpus: dict[str, int] = field(default_factory=dict)
    #: leaf switch -> the job's hosts under it, in allocation order ({}: no switch tree)
    switches: dict[str, tuple[str, ...]] = field(default_factory=dict)
    #: host -> IPv4 address the other nodes reach it at (None: unknown here)
    addresses: dict[str, str | None] = field(default_factory=dict)

    @staticmethod
    def from_env(env: Mapping[str, str] = os.environ, scontrol: Callable[..., str] = _scontrol) -> SlurmJob:
        """The enclosing job, from Slurm's variables and `scontrol`; SlurmError outside one."""
        job_id, nodelist = env.get(JOB_ENV) or "manual", env.get("SLURM_JOB_NODELIST")
        if not nodelist:
            raise SlurmError("not inside a Slurm job (SLURM_JOB_NODELIST is not set): submit with sbatch or salloc")
        try:
            hosts = expand_hostlist(nodelist)
        except ValueError as err:
            raise SlurmError(f"SLURM_JOB_NODELIST: {err}") from None
        this = env.get("SLURMD_NODENAME")
        cpus: dict[str, int] = {}
        if env.get("SLURM_JOB_CPUS_PER_NODE"):
            try:
                cpus = parse_cpus_per_node(env["SLURM_JOB_CPUS_PER_NODE"], hosts)
            except ValueError as err:
                raise SlurmError(str(err)) from None
        gpus = parse_job_gpus(scontrol("show", "job", "-d", job_id))
        if not gpus and this in hosts and env.get("SLURM_GPUS_ON_NODE", "0").isdigit() and int(env.get("SLURM_GPUS_ON_NODE", "0")):
            gpus = {h: int(env["SLURM_GPUS_ON_NODE"]) for h in hosts}  # the job's nodes are alike
        tree = parse_switch_tree(scontrol("show", "topology"))
        switches = {name: tuple(h for h in hosts if h in members) for name, members in tree.items()}
        node_addr = parse_node_addresses(scontrol("show", "node", "-o", nodelist))
        addresses = {h: resolve_ipv4(node_addr.get(h, h)) for h in hosts}
        return SlurmJob(job_id=job_id, hosts=tuple(hosts), this_host=this if this in hosts else None, cpus=cpus,
                        gpus=gpus, switches={k: v for k, v in switches.items() if v}, addresses=addresses)

    def racks(self) -> list[tuple[str, list[str]]]:
        """(rack name, hosts) with the first host's rack first: one rack per leaf switch holding
        hosts of the job (named after it), hosts under no leaf in one rack ``job<id>``; without a
        switch tree, one rack of every host."""
        rack_of: dict[str, str] = {}
        for switch, members in self.switches.items():
            for h in members:
                rack_of.setdefault(h, _rack_name(switch))
        racks: dict[str, list[str]] = {}
        for h in self.hosts:
            racks.setdefault(rack_of.get(h, f"job{self.job_id}"), []).append(h)
        return list(racks.items())


def _rack_name(switch: str) -> str:
    """A switch name as a rack name (a key chunk: letters, digits, '_', '.', '-')."""
    name = re.sub(r"[^A-Za-z0-9_.-]", "-", switch).lstrip("-_.") or "switch"
    return name[:64]


# ----------------------------------------------------------------------------------------------
# The generated topology


@dataclass(frozen=True, kw_only=True)
class GenerateSettings:
    """What scripts/slurm/dvla.sbatch asks of the generated topology (its DVLA_* variables)."""

    run: str
    python: str
    task_env: str = "PushCube-v1"
    rollouts_per_node: int = 2
    max_env_steps: int = 400000
    base_port: int = 17400
    remote_workdir: str = "/tmp/dvla"
    #: the `task:` mapping to use instead of ``{env: task_env}`` (its budget's max_env_steps is
    #: set to `max_env_steps`), e.g. a topology file's task section
    task: dict | None = None
    #: "auto", "ssh" or "slurm" (written as the topology's `launcher`)
    launcher: str = "auto"
    #: a dry run: a host without an address is left without one instead of refused
    dry_run: bool = False


def generate_topology(job: SlurmJob, s: GenerateSettings) -> tuple[str, list[str]]:
    """(topology YAML, notes) for `job`: the first host runs the actor (one per GPU there: the
    learner group's ranks), a replicator and the evaluator; every other host a replicator and
    its rollouts. Racks follow the leaf switches. SlurmError for a host with no address (the
    notes say so instead in a dry run)."""
    notes = []
    for h in job.hosts:
        if job.addresses.get(h) is None:
            if not s.dry_run:
                raise SlurmError(f"cannot resolve {h} to an IPv4 address (NodeAddr in scontrol show node, or the resolver)")
            notes.append(f"{h} does not resolve here: no address for it in this dry run")
    head = job.hosts[0]
    lines = [f"# generated by python -m dvla.orchestrator.slurm for job {job.job_id} on {','.join(job.hosts)}",
             f"run: {s.run}", f"base_port: {s.base_port}"]
    if s.launcher != "auto":
        lines.append(f"launcher: {s.launcher}")
    task = dict(s.task) if s.task is not None else {"env": s.task_env}
    task["budget"] = {**(task.get("budget") or {}), "max_env_steps": s.max_env_steps}
    if job.gpus:
        task.setdefault("device", "cuda")
    lines.append("task: " + json.dumps(task))  # JSON is YAML: one line, every value quoted as needed
    lines += ["ssh:", f"  python: {s.python}", f"  workdir: {s.remote_workdir}", "racks:"]
    index = {h: i for i, h in enumerate(job.hosts)}
    for rack, hosts in job.racks():
        lines += [f"  - name: {rack}", "    nodes:"]
        for h in hosts:
            lines += [f"      - name: n{index[h]}", f"        host: {h}"]
            if job.addresses.get(h):
                lines.append(f"        address: {job.addresses[h]}")
            if h == head:
                actors = max(1, job.gpus.get(h, 0))
                lines.append(f"        roles: [{{role: actor, count: {actors}}}, {{role: replicator}}, {{role: evaluator}}]")
            else:
                rollouts = s.rollouts_per_node
                lines.append(f"        roles: [{{role: replicator}}, {{role: rollout, count: {rollouts}}}]")
    return "\n".join(lines) + "\n", notes


# ----------------------------------------------------------------------------------------------
# Choosing the launcher


def slurm_job_for(topo: Topology, env: Mapping[str, str] = os.environ) -> SlurmJob | None:
    """The job whose steps run `topo`'s roles, or None when the SSH launcher (or none) applies:
    ``launcher: slurm`` needs a job; ``auto`` takes one when there is one (and no netns emulation)."""
    if topo.launcher == "ssh" or (topo.launcher == "auto" and (topo.emulate == "netns" or not env.get(JOB_ENV))):
        return None
    if shutil.which("srun") is None:
        if topo.launcher == "slurm":
            raise SlurmError(f"{topo.source}: launcher: slurm but srun is not on PATH")
        return None
    try:
        return SlurmJob.from_env(env)
    except SlurmError as err:
        raise SlurmError(f"{topo.source}: launcher: {topo.launcher}: {err}") from None


# ----------------------------------------------------------------------------------------------
# Launching roles as job steps


class StepTarget(SshTarget):
    """A node of the job, as messages name it (its `ssh` settings give only python and workdir)."""

    def label(self) -> str:
        return f"{self.host} (Slurm step)"


class SlurmWrapper(SshWrapper):
    """Starts each role as a step of `job` on its node; the roles of this host work in the run
    directory itself, those of other hosts in ``ssh.workdir`` there (results sent back as with SSH).
    A node on this host when this host is no node of the job (salloc's login shell) runs its roles
    as plain local processes through `local`."""

    def __init__(self, topo: Topology, secret_hex: str, env: dict[str, str], job: SlurmJob, run_dir: Path,
                 local: CommandWrapper | None = None) -> None:
        super().__init__(topo, secret_hex, env, local)
        self.job = job
        self.run_dir = run_dir
        self.srun = shutil.which("srun") or "srun"
        #: node name -> (Slurm host, SSH settings: python and workdir) of every node run as steps
        self.targets = {}
        for _rack, node in topo.nodes():
            host = self.slurm_host(node.host)
            if host is not None:
                self.targets[node.name] = StepTarget(host, topo.ssh_for(node))

    def slurm_host(self, host: str) -> str | None:
        """The job's host a topology host names (this one for "localhost"), or None: a local
        host outside the job."""
        if is_local_host(host) or host == self.job.this_host:
            return self.job.this_host
        return host

    def check_all(self) -> None:
        """Every node's host is one of the job's: one line naming the first that is not."""
        for _rack, node in self.topo.nodes():
            host = self.slurm_host(node.host)
            if host is not None and host not in self.job.hosts:
                raise SlurmError(f"{self.topo.source}: node {node.name}: host {host!r} is not a node of Slurm job "
                                 f"{self.job.job_id} ({', '.join(self.job.hosts)})")

    def in_place(self, target: SshTarget) -> bool:
        return target.host == self.job.this_host

    def remote_run_dir(self, target: SshTarget) -> str:
        return str(self.run_dir) if self.in_place(target) else super().remote_run_dir(target)

    def step_argv(self, proc: Process, host: str, python: str) -> list[str]:
        """srun's command line for one role's step on `host`."""
        argv = [self.srun, f"--jobid={self.job.job_id}", "--nodes=1", "--ntasks=1", f"--nodelist={host}",
                # steps share the node's CPUs and memory with the other roles' steps and the batch step
                "--overlap", "--mem=0", f"--job-name={proc.config.name}", "--kill-on-bad-exit=0", "--quiet"]
        if host in self.job.cpus:
            argv.append(f"--cpus-per-task={self.job.cpus[host]}")  # all of them: roles pin themselves
        return argv + ["--", *shlex.split(python), "-m", "dvla.orchestrator.ssh", "serve"]

    # -- CommandWrapper ------------------------------------------------------------------------

    def __call__(self, proc: Process, argv: list[str]) -> list[str]:
        target = self.target(proc)
        if target is None:
            return self.local(proc, argv)
        python = sys.executable if self.in_place(target) else target.ssh.python
        return self.step_argv(proc, target.host, python)

    def child_env(self, proc: Process, env: dict[str, str]) -> dict[str, str]:
        if self.target(proc) is None:
            return self.local.child_env(proc, env)
        # srun exports its environment to the step: the secrets travel in the stdin header instead
        from ..fabric.identity import IDENTITY_ENV

        return {k: v for k, v in env.items() if k not in (proc.config.secret_env, IDENTITY_ENV)}

    def output_path(self, sup: Supervised) -> Path | None:
        target = self.target(sup.proc)
        if target is not None and self.in_place(target):
            return None  # its files are already in the run directory
        return super().output_path(sup)

    def finished(self, sup: Supervised, code: int) -> str | None:
        target = self.target(sup.proc)
        if target is not None and self.in_place(target):
            return None
        return super().finished(sup, code)


# ----------------------------------------------------------------------------------------------
# `python -m dvla.orchestrator.slurm topology OUT`


def _task_section(path: str) -> dict:
    """The `task:` mapping of a YAML file (ValueError naming the file when there is none)."""
    import yaml

    doc = yaml.safe_load(Path(path).read_text())
    if not isinstance(doc, dict) or not isinstance(doc.get("task"), dict):
        raise ValueError(f"DVLA_TASK_FILE={path}: no task: mapping in it")
    return doc["task"]


def main(argv: list[str] | None = None) -> int:
    """Write the generated topology of the enclosing job to OUT (its notes to stderr). Settings:
    DVLA_RUN, DVLA_PYTHON, DVLA_TASK_ENV, DVLA_ROLLOUTS_PER_NODE, DVLA_MAX_ENV_STEPS,
    DVLA_BASE_PORT, DVLA_REMOTE_WORKDIR, DVLA_LAUNCHER, DVLA_DRY_RUN, DVLA_TASK_FILE (a YAML
    file whose `task:` mapping, a topology's for one, replaces DVLA_TASK_ENV)."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2 or args[0] != "topology":
        print("usage: python -m dvla.orchestrator.slurm topology OUT (inside a Slurm job)", file=sys.stderr)
        return 2
    env = os.environ
    try:
        job = SlurmJob.from_env(env)
        if len(job.hosts) < 2:
            raise SlurmError(f"needs at least 2 nodes, got {len(job.hosts)} ({env['SLURM_JOB_NODELIST']}); "
                             "on one node give the script a topology file (topologies/local.yaml)")
        settings = GenerateSettings(
            run=env.get("DVLA_RUN") or f"slurm-{job.job_id}", python=env.get("DVLA_PYTHON") or sys.executable,
            task_env=env.get("DVLA_TASK_ENV", "PushCube-v1"),
            rollouts_per_node=int(env.get("DVLA_ROLLOUTS_PER_NODE", "2")),
            max_env_steps=int(env.get("DVLA_MAX_ENV_STEPS", "400000")),
            base_port=int(env.get("DVLA_BASE_PORT", "17400")),
            remote_workdir=env.get("DVLA_REMOTE_WORKDIR") or f"/tmp/{env.get('USER', 'dvla')}/dvla-{job.job_id}",
            launcher=env.get("DVLA_LAUNCHER", "auto"), dry_run=bool(env.get("DVLA_DRY_RUN")),
            task=_task_section(env["DVLA_TASK_FILE"]) if env.get("DVLA_TASK_FILE") else None)
        text, notes = generate_topology(job, settings)
    except (SlurmError, ValueError, OSError) as err:
        print(f"dvla slurm: {err}", file=sys.stderr)
        return 2
    for note in notes:
        print(f"dvla slurm: {note}", file=sys.stderr)
    Path(args[1]).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A real multi-node Slurm cluster on one machine: slurmctld in the root network namespace and one
slurmd per network namespace, each namespace a host of its own (its address on a bridge, its UTS
hostname), one munged for all (a namespace does not isolate the filesystem, so every slurmd reaches
its socket). docs/slurm.md lists what was needed and why (``nsenter --net``, not ``ip netns exec``,
which remounts /sys without a cgroup filesystem and so stops slurmd).

Everything lives under one temporary directory; namespaces, bridge and veths carry a per-cluster
tag. :meth:`MultiNodeSlurm.stop` removes all of it (by pid and by name) whatever state it is in.
"""

from __future__ import annotations

import os
import random
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

#: daemons live in sbin, which a non-login root shell may leave out of PATH
SEARCH_PATH = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/sbin"])
#: the daemons and clients the cluster needs (Debian: slurm-wlm, munge; util-linux; iproute2)
TOOLS = ("munged", "slurmctld", "slurmd", "sbatch", "srun", "scontrol", "sinfo", "scancel", "squeue",
         "nsenter", "unshare", "hostname", "ip")
#: `scontrol show job` states after which a job does nothing more
FINAL_STATES = {"COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "PREEMPTED",
                "BOOT_FAIL", "DEADLINE"}


def tool(name: str) -> str:
    path = shutil.which(name, path=SEARCH_PATH)
    if path is None:
        raise FileNotFoundError(name)
    return path


def missing_tools() -> list[str]:
    return [t for t in TOOLS if shutil.which(t, path=SEARCH_PATH) is None]


def client_env(**extra: str) -> dict[str, str]:
    """This environment without an enclosing job's SLURM_* settings, plus `extra`."""
    return {**{k: v for k, v in os.environ.items() if not k.startswith("SLURM_")}, **extra}


def tail(path: Path, n: int = 20) -> str:
    return "\n".join(path.read_text(errors="replace").splitlines()[-n:]) if path.exists() else f"({path} missing)"


def _free_subnet() -> int:
    """A third octet k such that 10.79.k.0/24 is not routed here yet."""
    routes = subprocess.run([tool("ip"), "-4", "route"], capture_output=True, text=True).stdout
    for _ in range(100):
        k = random.randrange(1, 254)
        if f"10.79.{k}." not in routes:
            return k
    raise RuntimeError("no free 10.79.k.0/24 subnet")


def _free_port_pair() -> int:
    for _ in range(100):
        port = random.randrange(20000, 60000)
        ok = True
        for p in (port, port + 1):
            with socket.socket() as s:
                try:
                    s.bind(("0.0.0.0", p))
                except OSError:
                    ok = False
        if ok:
            return port
    raise RuntimeError("no free port pair")


class SlurmDaemons:
    """What every test cluster has: a temporary directory (not pytest's tmp_path: munged wants every
    directory above its socket searchable by all), a munged on its own socket, the daemons started
    with :meth:`_spawn` and waited for with :meth:`_wait`, clients run with :meth:`run`."""

    def __init__(self, prefix: str) -> None:
        self.root = Path(tempfile.mkdtemp(prefix=prefix))
        self.root.chmod(0o755)
        self.socket = self.root / "munge" / "munge.socket"
        self.conf = self.root / "slurm.conf"
        self.daemons: dict[str, subprocess.Popen] = {}

    def env(self, **extra: str) -> dict[str, str]:
        """The environment of a Slurm client of this cluster."""
        return client_env(SLURM_CONF=str(self.conf), PATH=SEARCH_PATH, **extra)

    def run(self, *cmd: str, timeout: float = 30, **kw) -> subprocess.CompletedProcess:
        return subprocess.run([tool(cmd[0]), *cmd[1:]], capture_output=True, text=True, env=self.env(),
                              timeout=timeout, **kw)

    def _start_munge(self) -> None:
        keydir, sockdir = self.root / "munge-key", self.socket.parent
        keydir.mkdir(mode=0o700)
        sockdir.mkdir(mode=0o755)
        key = keydir / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o400)
        self._spawn("munged", [tool("munged"), "--foreground", f"--key-file={key}", f"--socket={self.socket}",
                               f"--pid-file={sockdir}/munged.pid", f"--log-file={keydir}/munged.log",
                               f"--seed-file={keydir}/munged.seed"])
        self._wait(self.socket.exists, 15, "munged never created its socket")

    def _spawn(self, name: str, cmd: list[str]) -> None:
        with open(self.root / f"{name}.out", "wb") as out:
            self.daemons[name] = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=self.env())

    def _wait(self, ready, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            dead = [n for n, p in self.daemons.items() if p.poll() is not None]
            if dead:
                raise RuntimeError(f"{dead[0]} exited: {tail(self.root / f'{dead[0]}.out')}\n{self.logs()}")
            if ready():
                return
            time.sleep(0.5)
        raise RuntimeError(f"{what} within {timeout:.0f} s\n{self.logs()}")

    def logs(self, n: int = 20) -> str:
        files = sorted(self.root.glob("*.out")) + sorted(self.root.glob("*.log"))
        return "\n".join(f"--- {p.name}\n{tail(p, n)}" for p in files)

    def jobs(self, *job_id: str) -> list[dict[str, str]]:
        """`scontrol show job -o`'s fields of every job, or of one (no accounting database:
        slurmctld's own records, kept for MinJobAge after a job ends)."""
        out = self.run("scontrol", "show", "job", "-o", *job_id).stdout
        return [dict(f.split("=", 1) for f in line.split() if "=" in f)
                for line in out.splitlines() if "JobId=" in line]

    def job(self, job_id: str) -> dict[str, str]:
        found = self.jobs(job_id)
        return found[0] if found else {}


class MultiNodeSlurm(SlurmDaemons):
    """munged, slurmctld and `n` slurmd's, each in a network namespace, under one temporary directory.

    `switches` groups the nodes (by index) under leaf switches of a `topology/tree`."""

    def __init__(self, n: int = 3, switches: tuple[tuple[int, ...], ...] = ((0,), (1, 2)), cpus: int | None = None) -> None:
        self.tag = f"{random.randrange(16 ** 4):04x}"
        self.nodes = [f"dn{self.tag}{i}" for i in range(n)]
        self.switches = switches
        self.cpus = cpus or os.cpu_count() or 1
        self.subnet = _free_subnet()
        self.bridge = f"dvsb{self.tag}"
        self.gateway = f"10.79.{self.subnet}.1"
        self.addresses = {node: f"10.79.{self.subnet}.{10 + i}" for i, node in enumerate(self.nodes)}
        self.netns = {node: f"dvs{self.tag}n{i}" for i, node in enumerate(self.nodes)}
        super().__init__("dvla-slurm-mn-")
        self.made_netns: list[str] = []
        self.made_bridge = False

    # -- start ---------------------------------------------------------------------------------

    def start(self) -> None:
        self._network()
        self._start_munge()
        port = _free_port_pair()
        for d in ("state", "spool"):
            (self.root / d).mkdir(mode=0o700)
        (self.root / "plugstack.conf").write_text("")  # not the system's /etc/slurm/plugstack.conf
        r = self.root
        nodes = [f"NodeName={n} NodeAddr={a} CPUs={self.cpus} State=UNKNOWN" for n, a in self.addresses.items()]
        self.conf.write_text("\n".join([
            "ClusterName=dvlamn",
            # the controller must be this machine's real hostname; its address the bridge's
            f"SlurmctldHost={socket.gethostname()}({self.gateway})",
            "SlurmUser=root",
            "SlurmdUser=root",
            f"SlurmctldPort={port}",
            f"SlurmdPort={port + 1}",
            "AuthType=auth/munge",
            "CredType=cred/munge",
            f"AuthInfo=socket={self.socket}",
            f"StateSaveLocation={r}/state",
            f"SlurmdSpoolDir={r}/spool.%n",
            f"SlurmctldPidFile={r}/slurmctld.pid",
            f"SlurmdPidFile={r}/slurmd.%n.pid",
            f"SlurmctldLogFile={r}/slurmctld.log",
            f"SlurmdLogFile={r}/slurmd.%n.log",
            f"PlugStackConfig={r}/plugstack.conf",
            "ProctrackType=proctrack/linuxproc",
            "TaskPlugin=task/none",
            "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_Core",
            "TopologyPlugin=topology/tree",
            "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none",
            "JobCompType=jobcomp/none",
            "MpiDefault=none",
            "ReturnToService=2",
            "MinJobAge=300",
            *nodes,
            f"PartitionName=dvla Nodes={','.join(self.nodes)} Default=YES MaxTime=INFINITE State=UP",
            "",
        ]))
        leaves = [f"SwitchName=leaf{i} Nodes={','.join(self.nodes[j] for j in group)}"
                  for i, group in enumerate(self.switches)]
        top = f"SwitchName=top Switches={','.join(f'leaf{i}' for i in range(len(self.switches)))}"
        (self.root / "topology.conf").write_text("\n".join([*leaves, top, ""]))
        self._spawn("slurmctld", [tool("slurmctld"), "-D", "-f", str(self.conf)])
        for node in self.nodes:
            # its own network namespace and hostname; `-N` names it in slurm.conf
            self._spawn(f"slurmd.{node}", [
                tool("nsenter"), f"--net=/run/netns/{self.netns[node]}", tool("unshare"), "--uts", "sh", "-c",
                f'hostname {node} && exec {tool("slurmd")} -D -N {node} -f {self.conf}'])
        self._wait(self._all_idle, 60, "nodes never all idle in sinfo")

    def _all_idle(self) -> bool:
        out = self.run("sinfo", "-h", "-N", "-o", "%N %T").stdout.split()
        states = dict(zip(out[::2], out[1::2]))
        return all(states.get(n) == "idle" for n in self.nodes)

    def _network(self) -> None:
        ip = tool("ip")
        subprocess.run([ip, "link", "add", self.bridge, "type", "bridge"], check=True)
        self.made_bridge = True
        subprocess.run([ip, "addr", "add", f"{self.gateway}/24", "dev", self.bridge], check=True)
        subprocess.run([ip, "link", "set", self.bridge, "up"], check=True)
        for i, node in enumerate(self.nodes):
            ns, host_end, ns_end = self.netns[node], f"dvs{self.tag}h{i}", f"dvs{self.tag}p{i}"
            subprocess.run([ip, "netns", "add", ns], check=True)
            self.made_netns.append(ns)
            subprocess.run([ip, "link", "add", host_end, "type", "veth", "peer", "name", ns_end], check=True)
            subprocess.run([ip, "link", "set", host_end, "master", self.bridge, "up"], check=True)
            subprocess.run([ip, "link", "set", ns_end, "netns", ns], check=True)
            for args in (["link", "set", "lo", "up"], ["link", "set", ns_end, "name", "eth0"],
                         ["addr", "add", f"{self.addresses[node]}/24", "dev", "eth0"], ["link", "set", "eth0", "up"],
                         ["route", "add", "default", "via", self.gateway]):
                subprocess.run([ip, "-n", ns, *args], check=True)

    # -- jobs ----------------------------------------------------------------------------------

    def steps(self, job_id: str) -> list[dict[str, str]]:
        """The job's running steps, `squeue -s`: step id, name and node list each."""
        out = self.run("squeue", "-h", "-s", "-j", job_id, "-o", "%i|%j|%N").stdout
        return [dict(zip(("id", "name", "nodes"), line.split("|"))) for line in out.splitlines() if line.strip()]

    # -- stop ----------------------------------------------------------------------------------

    def stop(self) -> None:
        """Cancel what still runs, stop the daemons by pid (newest first), delete the namespaces,
        the bridge and the directory. Each part runs whatever the others did."""
        try:
            if "slurmctld" in self.daemons and self.daemons["slurmctld"].poll() is None:
                live = [j["JobId"] for j in self.jobs() if j.get("JobState") not in FINAL_STATES]
                if live:
                    self.run("scancel", *live)
                    deadline = time.monotonic() + 30
                    while time.monotonic() < deadline and not all(
                            self.job(j).get("JobState") in FINAL_STATES for j in live):
                        time.sleep(0.5)
        except (subprocess.SubprocessError, OSError):
            pass
        for _name, proc in reversed(self.daemons.items()):
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        self._kill_in_namespaces()
        for i, ns in enumerate(self.made_netns):
            # the host end first: deleting it deletes its peer at once, whereas a namespace (and
            # the veth in it) lingers until the kernel has let go of its last process
            subprocess.run([tool("ip"), "link", "del", f"dvs{self.tag}h{i}"], capture_output=True)
            subprocess.run([tool("ip"), "netns", "del", ns], capture_output=True)
        if self.made_bridge:
            subprocess.run([tool("ip"), "link", "del", self.bridge], capture_output=True)
        shutil.rmtree(self.root, ignore_errors=True)

    def _kill_in_namespaces(self) -> None:
        """SIGKILL whatever still runs in one of the cluster's namespaces (a role a job left)."""
        for ns in self.made_netns:
            pids = subprocess.run([tool("ip"), "netns", "pids", ns], capture_output=True, text=True).stdout.split()
            for pid in pids:
                try:
                    os.kill(int(pid), 9)
                except (ProcessLookupError, ValueError):
                    pass

    def leftovers(self) -> list[str]:
        """What of the cluster is still there (namespaces, links, directory), one line each."""
        out = []
        names = subprocess.run([tool("ip"), "netns", "list"], capture_output=True, text=True).stdout
        out += [f"netns {ns}" for ns in self.made_netns if ns in names]
        links = subprocess.run([tool("ip"), "-o", "link"], capture_output=True, text=True).stdout
        out += [f"link {self.bridge}" for _ in [0] if f" {self.bridge}:" in links or f"dvs{self.tag}" in links]
        if self.root.exists():
            out.append(f"directory {self.root}")
        return out

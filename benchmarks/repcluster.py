"""A weight tree of real processes on an emulated cluster, driven from this process.

:class:`RepCluster` plans a topology with the orchestrator's planner (same names, ports, parents
and Zenoh link graph as `dvla up`), builds its network namespaces when the topology asks for
``emulate: netns``, and starts one :mod:`benchmarks.repnode` process per actor / replicator /
rollout slot (source / relay / sink). Evaluators are left out. The driver triggers versions,
reads every node's status over the control plane, kills and restarts processes.

Used by `dvla bench replication` and by the replication tests on the emulated cluster.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from dvla.config import Topology
from dvla.fabric import Fabric, new_secret
from dvla.fabric.messages import RoleStatus
from dvla.orchestrator.launcher import Launcher, Supervised, log_tail
from dvla.orchestrator.plan import Plan, make_plan
from dvla.orchestrator.run import tool_fabric
from .repnode import write_trigger
from .stats import process_cpu_s

log = logging.getLogger("dvla.repcluster")

MODE_OF_KIND = {"actor": "source", "replicator": "relay", "rollout": "sink"}


def without_roles(topo: Topology, kinds: set[str]) -> Topology:
    """`topo` with every placement of the given role kinds removed (nodes left empty are kept)."""
    racks = []
    for rack in topo.racks:
        nodes = [dataclasses.replace(n, roles=tuple(r for r in n.roles if r.role not in kinds)) for n in rack.nodes]
        racks.append(dataclasses.replace(rack, nodes=tuple(nodes)))
    return dataclasses.replace(topo, racks=tuple(racks))


class _RepLauncher(Launcher):
    """The orchestrator's launcher, starting repnode processes instead of roles."""

    def __init__(self, *args: Any, numel: int, faults: dict[str, list[str]], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.numel = numel
        self.faults = faults

    def command(self, sup: Supervised) -> list[str]:
        cfg = sup.proc.config
        argv = [sys.executable, "-m", "benchmarks.repnode", "--mode", MODE_OF_KIND[cfg.kind],
                "--config", str(sup.config_path), "--numel", str(self.numel)]
        for fault in self.faults.get(cfg.name, []):
            argv += ["--fault", fault]
        return self.wrap(sup.proc, argv) if self.wrap is not None else argv


class RepCluster:
    """Sources, relays and sinks of one topology, started and watched from here."""

    def __init__(
        self,
        topo: Topology,
        run_dir: Path,
        numel: int,
        *,
        faults: dict[str, list[str]] | None = None,
        netns: Any = None,
    ) -> None:
        self.topo = without_roles(topo, {"evaluator"})
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.numel = numel
        self.plan: Plan = make_plan(self.topo, str(self.run_dir))
        self.secret = new_secret()
        self._own_netns = netns is None and self.topo.emulate == "netns"
        self.netns = netns
        env = dict(os.environ, DVLA_SECRET=self.secret, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
        self.launcher = _RepLauncher(self.run_dir, env, max_restarts=0, numel=numel, faults=faults or {})
        self.fabric: Fabric | None = None

    # -- names --------------------------------------------------------------------------------
    def names(self, kind: str) -> list[str]:
        return [p.config.name for p in self.plan.processes if p.config.kind == kind]

    @property
    def source(self) -> str:
        return self.plan.root_actor

    @property
    def sinks(self) -> list[str]:
        return self.names("rollout")

    @property
    def relays(self) -> list[str]:
        return self.names("replicator")

    def children_of(self, name: str) -> list[str]:
        return list(self.plan.by_name(name).config.children)

    # -- lifecycle ----------------------------------------------------------------------------
    def start(self, timeout_s: float = 60.0) -> None:
        write_trigger(self.run_dir, 0)
        try:
            if self.topo.emulate == "netns":
                from dvla.orchestrator.netns import NetnsCluster, NetnsWrapper

                if self.netns is None:
                    self.netns = NetnsCluster(self.topo, self.plan)
                    self.netns.create()
                self.launcher.wrap = NetnsWrapper()
            for p in self.plan.processes:
                self.launcher.add(p)
            self.launcher.start_all()
            self.fabric = tool_fabric(self.topo.run, self.plan.ctrl_entry, bytes.fromhex(self.secret), name="repbench")
            self.wait_alive([p.config.name for p in self.plan.processes], timeout_s)
        except BaseException:
            self.close()
            raise

    def wait_alive(self, names: list[str], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        missing = set(names)
        while time.monotonic() < deadline:
            self._check_running()
            missing = set(names) - self.fabric.alive_members(timeout=1.0)  # type: ignore[union-attr]
            if not missing:
                return
            time.sleep(0.2)
        raise TimeoutError(f"not alive after {timeout_s:.0f} s: {', '.join(sorted(missing))} (logs in {self.run_dir / 'logs'})")

    def _check_running(self) -> None:
        for sup in self.launcher.children.values():
            if sup.popen is not None and sup.popen.poll() is not None:
                tail = log_tail(sup.log_path)
                raise RuntimeError(f"{sup.name} exited with {sup.popen.returncode}; last log lines:\n{tail}")

    def close(self) -> None:
        try:
            if self.fabric is not None:
                self.fabric.close()
                self.fabric = None
            names = list(self.launcher.children)
            self.launcher.stop(names, timeout=10.0)
            self.launcher.kill_all()
        finally:
            if self._own_netns and self.netns is not None:
                self.netns.destroy()

    def keep_netns(self) -> Any:
        """Leave the namespaces standing at close and return them (the caller removes them)."""
        self._own_netns = False
        return self.netns

    def __enter__(self) -> "RepCluster":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- driving ------------------------------------------------------------------------------
    def publish(self, upto_version: int) -> None:
        """Ask the source to publish versions until it has published `upto_version`."""
        write_trigger(self.run_dir, upto_version)

    def status(self, name: str, timeout: float = 2.0) -> RoleStatus | None:
        assert self.fabric is not None
        for _sender, st in self.fabric.query(self.fabric.keys.status(name), expect=RoleStatus, timeout=timeout):
            return st
        return None

    def statuses(self, names: list[str]) -> dict[str, RoleStatus | None]:
        return {n: self.status(n) for n in names}

    def wait_held(self, version: int, names: list[str] | None = None, timeout_s: float = 60.0, poll_s: float = 0.1) -> dict[str, dict[str, Any]]:
        """Wait until every named sink holds `version` (or later); returns their status extras."""
        names = self.sinks if names is None else names
        deadline = time.monotonic() + timeout_s
        done: dict[str, dict[str, Any]] = {}
        while time.monotonic() < deadline:
            for n in names:
                if n in done:
                    continue
                st = self.status(n, timeout=1.0)
                if st is not None and st.policy_version >= version:
                    done[n] = dict(st.extra)
            if len(done) == len(names):
                return done
            time.sleep(poll_s)
        versions = {n: getattr(self.status(n, 1.0), "policy_version", None) for n in names if n not in done}
        raise TimeoutError(f"v{version} not held after {timeout_s:.0f} s by: {versions}")

    def published(self) -> dict[str, dict[str, Any]]:
        st = self.status(self.source)
        if st is None:
            raise RuntimeError(f"source {self.source} does not answer status queries")
        return dict(st.extra.get("published", {}))

    def kill(self, name: str) -> None:
        """kill -9 one process (no clean shutdown: its sockets just vanish)."""
        sup = self.launcher.children[name]
        if sup.popen is None:
            raise RuntimeError(f"{name} is not running")
        os.kill(sup.popen.pid, signal.SIGKILL)
        sup.popen.wait(timeout=10)
        sup.popen = None

    def restart(self, name: str) -> None:
        sup = self.launcher.children[name]
        if sup.popen is not None and sup.popen.poll() is None:
            raise RuntimeError(f"{name} is still running")
        sup.restarts += 1
        self.launcher.start(sup)

    def cpu_seconds(self) -> float:
        """User + system CPU seconds used so far by the cluster's live processes (from /proc)."""
        return sum(self.cpu_by_process().values())

    def cpu_by_process(self) -> dict[str, float]:
        """User + system CPU seconds used so far by each live process of the cluster."""
        cpu = {name: process_cpu_s(pid) for name, pid in self.launcher.pids().items()}
        return {name: s for name, s in cpu.items() if s is not None}

    def node_tx_bytes(self, name: str) -> int | None:
        """Bytes sent so far by the NIC (eth0) of the node `name` runs on; None without netns."""
        proc = self.plan.by_name(name)
        if proc.netns is None:
            return None
        out = subprocess.run(["ip", "-n", proc.netns, "-s", "-j", "link", "show", "eth0"],
                             capture_output=True, text=True, check=True, timeout=10).stdout
        return int(json.loads(out)[0]["stats64"]["tx"]["bytes"])



"""Chaos on a training run: `dvla up` of an emulated cluster while rollouts, a replicator and the
actor are killed with SIGKILL on a schedule and one rack uplink drops packets at random.

What it measures, per fault: time from the kill to its detection (the role's liveliness token
gone, as the ctrl plane shows it; the launcher reporting the exit), to the restart (a new pid; the
token back) and to the restarted role holding the latest weights. What it checks at the end:
learning went on after every fault (new versions; eval return before and after), every live
replica holds the actor's latest version bit for bit (same checksum), policy versions never went
backwards in any role incarnation, and the run's chunk accounting closes exactly with every loss
inside its killed incarnation's bound.

    python -m benchmarks.chaos --json bench-results/chaos.json            # the 5-minute profile
    dvla bench chaos --quick --json bench-results/chaos-quick.json        # the short CI profile

Needs root (network namespaces, iptables in the emulated fabric's namespace).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import yaml

ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True, kw_only=True)
class Profile:
    """A fault schedule; times are seconds after the cluster is warm (the actor at `warm_version`)."""

    #: name reported in the results
    name: str
    #: seconds of the fault window
    faults_s: float
    #: kill -9 a random rollout at these times
    rollout_kills_s: tuple[float, ...]
    #: kill -9 one replicator at this time (None: never)
    replicator_kill_s: float | None
    #: kill -9 the actor at this time (None: never)
    actor_kill_s: float | None
    #: probability of dropping each packet crossing the lossy rack's uplink, both directions
    loss: float = 0.05
    #: index of the rack whose uplink loses packets
    loss_rack: int = 1
    #: the actor's published version that counts as warm (faults start then)
    warm_version: int = 3
    #: seconds after the fault window for the last restarted roles to catch up (a restart takes
    #: 40-100 s on a loaded 2-core machine: imports, env creation, sessions)
    settle_s: float = 60.0
    #: seed of the choice of rollouts to kill
    seed: int = 1


#: kill -9 a random rollout every 30 s for 5 minutes, one replicator once, the actor once
FULL = Profile(name="full", faults_s=300.0, rollout_kills_s=tuple(float(t) for t in range(30, 301, 30)),
               replicator_kill_s=45.0, actor_kill_s=135.0, settle_s=150.0)
#: one fault of each kind, loss on (the default test suite's profile): the faults 10 s apart, then
#: as long as the restarted roles need to catch up (the trackers end the settling, not a clock)
QUICK = Profile(name="quick", faults_s=35.0, rollout_kills_s=(5.0,), replicator_kill_s=15.0, actor_kill_s=25.0,
                settle_s=95.0)


def chaos_topology(src: Path, out_dir: Path, run: str) -> Path:
    """The topology under test with its own run id and no success stop (the faults decide the length)."""
    doc = yaml.safe_load(src.read_text())
    doc["run"] = run
    budget = doc.setdefault("task", {}).setdefault("budget", {})
    budget.pop("until_success", None)
    budget.pop("consecutive", None)
    budget["max_env_steps"] = 10**9
    path = out_dir / f"{run}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


# ----------------------------------------------------------------------------------------------
# Packet loss on a rack uplink


class UplinkLoss:
    """Random drops on one rack's uplink veth, inside the emulated fabric's namespace.

    The uplink is a bridge port, so the rules match bridged frames by physical port (the kernel's
    bridge netfilter hook, on in a fresh namespace): one rule per direction.
    """

    def __init__(self, run: str, rack: int, probability: float) -> None:
        from dvla.orchestrator.netns import fabric_name, uplink_ends

        self.ns = fabric_name(run)
        self.port = uplink_ends(rack)[0]
        self.probability = probability
        self.rules = [
            ["-m", "physdev", f"--physdev-{d}", self.port, "-m", "statistic", "--mode", "random",
             "--probability", f"{probability}", "-j", "DROP"]
            for d in ("in", "out")
        ]
        self.installed = False

    def _iptables(self, *args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["ip", "netns", "exec", self.ns, "iptables", *args], capture_output=True, text=True,
                              timeout=30)

    def install(self) -> None:
        for rule in self.rules:
            r = self._iptables("-A", "FORWARD", *rule)
            if r.returncode != 0:
                raise RuntimeError(f"iptables in {self.ns}: {r.stderr.strip()}")
        self.installed = True

    def dropped_packets(self) -> int:
        """Packets the rules dropped so far (proof that the loss was applied)."""
        r = self._iptables("-L", "FORWARD", "-v", "-n", "-x")
        total = 0
        for line in r.stdout.splitlines():
            cols = line.split()
            if "statistic" in line and cols and cols[0].isdigit():
                total += int(cols[0])
        return total

    def remove(self) -> None:
        if self.installed:
            for rule in self.rules:
                self._iptables("-D", "FORWARD", *rule)
            self.installed = False


def iptables_usable() -> str | None:
    """None when this host can run the loss rules, else why not."""
    if os.geteuid() != 0:
        return "needs root"
    if shutil.which("iptables") is None or shutil.which("ip") is None:
        return "needs iptables and iproute2 (scripts/setup.sh installs them)"
    ns = f"dvchk{os.getpid() % 100000}"
    try:
        if subprocess.run(["ip", "netns", "add", ns], capture_output=True).returncode != 0:
            return "cannot create a network namespace"
        r = subprocess.run(["ip", "netns", "exec", ns, "iptables", "-A", "FORWARD", "-m", "statistic", "--mode",
                            "random", "--probability", "0.05", "-j", "DROP"], capture_output=True, text=True)
        return None if r.returncode == 0 else f"iptables statistic match unusable: {r.stderr.strip()}"
    finally:
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


# ----------------------------------------------------------------------------------------------
# Watching the run from outside: up's output, liveliness, status, evals


@dataclass
class Observations:
    lines: list[tuple[float, str]] = field(default_factory=list)  # (wall time, dvla up output line)
    alive: list[tuple[float, str, bool]] = field(default_factory=list)  # (wall time, role, alive)
    evals: list[dict[str, Any]] = field(default_factory=list)
    samples: list[tuple[float, dict[str, dict[str, Any]]]] = field(default_factory=list)  # status rounds
    lock: threading.Lock = field(default_factory=threading.Lock)


def _brief(st: Any) -> dict[str, Any]:
    e = st.extra
    return {
        "kind": st.kind, "pid": st.pid, "state": st.state, "policy_version": st.policy_version,
        "env_steps": st.env_steps, "published_version": e.get("published_version"),
        "published_checksum": e.get("published_checksum"), "held_version": e.get("held_version"),
        "held_checksum": e.get("held_checksum"), "planes": st.planes,
    }


class Watcher:
    """A ctrl-plane client of the run (its own session): liveliness, evals and status rounds."""

    def __init__(self, run: str, state: dict[str, Any], obs: Observations) -> None:
        from dvla.fabric.messages import EvalResult
        from dvla.orchestrator.run import state_fabric

        self.obs = obs
        # Through the relays first (the actor's router is the first entry): killing the actor then
        # does not cut this observer off while it counts the other faults.
        entry = tuple(state["ctrl_entry"][1:]) + tuple(state["ctrl_entry"][:1])
        self.fabric = state_fabric(state, "chaos-watch", entry)
        self.fabric.watch_alive(self._on_alive)
        self.fabric.on_ctrl(self.fabric.keys.eval_all(), EvalResult, self._on_eval)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, name="chaos-status", daemon=True)
        self._thread.start()

    def _on_alive(self, role: str, alive: bool) -> None:
        with self.obs.lock:
            self.obs.alive.append((time.time(), role, alive))

    def _on_eval(self, _sender: str, ev: Any) -> None:
        with self.obs.lock:
            self.obs.evals.append({"time": time.time(), "version": ev.policy_version, "return_mean": ev.return_mean,
                                   "success_once": ev.success_once})

    def round(self, timeout: float = 1.5) -> dict[str, dict[str, Any]]:
        from dvla.fabric.messages import RoleStatus

        replies = self.fabric.query(self.fabric.keys.status_all(), expect=RoleStatus, timeout=timeout)
        return {msg.name: _brief(msg) for _s, msg in replies}

    def role(self, name: str, timeout: float = 0.7) -> dict[str, Any] | None:
        from dvla.fabric.messages import RoleStatus

        replies = self.fabric.query(self.fabric.keys.status(name), expect=RoleStatus, timeout=timeout)
        return _brief(replies[0][1]) if replies else None

    def _poll(self) -> None:
        while not self._stop.is_set():
            t = time.time()
            try:
                snap = self.round()
            except Exception:  # the entry router restarting: try again next round
                snap = {}
            with self.obs.lock:
                self.obs.samples.append((t, snap))
            self._stop.wait(1.0)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.fabric.close()


# ----------------------------------------------------------------------------------------------
# The run


@dataclass
class Kill:
    kind: str
    role: str
    pid: int
    at: float  # wall time of the SIGKILL
    at_rel_s: float  # seconds into the fault window
    actor_version_before: int
    figures: dict[str, float | None] = field(default_factory=dict)


class ChaosRun:
    def __init__(self, topology: Path, profile: Profile, runs_root: Path, base_port: int | None,
                 progress: Callable[[str], None]) -> None:
        self.profile = profile
        self.progress = progress
        self.runs_root = runs_root
        self.run = "chaos8" if profile.name == "full" else f"chaos8{profile.name[0]}"
        runs_root.mkdir(parents=True, exist_ok=True)
        self.topology = chaos_topology(topology, runs_root, self.run)
        self.run_dir = runs_root / self.run
        self.base_port = base_port
        self.obs = Observations()
        self.kills: list[Kill] = []
        self.rng = random.Random(profile.seed)
        self.up: subprocess.Popen | None = None
        self.watcher: Watcher | None = None
        self.loss: UplinkLoss | None = None
        self._trackers: list[threading.Thread] = []

    # -- helpers ----------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        try:
            return json.loads((self.run_dir / "state.json").read_text())
        except (OSError, ValueError):
            return {}

    def _read_up(self) -> None:
        assert self.up is not None and self.up.stdout is not None
        for line in self.up.stdout:
            with self.obs.lock:
                self.obs.lines.append((time.time(), line.rstrip()))

    def _up_alive(self) -> None:
        if self.up is not None and self.up.poll() is not None:
            tail = "\n".join(line for _t, line in self.obs.lines[-20:])
            raise RuntimeError(f"dvla up exited early ({self.up.returncode}):\n{tail}")

    def _wait(self, pred: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self._up_alive()
            if pred():
                return
            time.sleep(0.5)
        raise RuntimeError(f"timed out after {timeout:.0f} s waiting for {what}")

    def latest(self) -> dict[str, dict[str, Any]]:
        with self.obs.lock:
            for _t, snap in reversed(self.obs.samples):
                if snap:
                    return snap
        return {}

    def actor_version(self) -> int:
        """The newest version the actor is known to have published (also while it restarts)."""
        with self.obs.lock:
            snaps = [snap for _t, snap in self.obs.samples]
        return max((int(s["published_version"] or 0) for snap in snaps for s in snap.values() if s["kind"] == "actor"),
                   default=-1)

    # -- phases -----------------------------------------------------------------------------
    def start(self) -> None:
        argv = [sys.executable, "-m", "dvla", "up", str(self.topology), "--runs", str(self.runs_root), "--quiet"]
        if self.base_port is not None:
            argv += ["--base-port", str(self.base_port)]
        self.progress(f"dvla up {self.topology.name} (run {self.run})")
        self.up = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        threading.Thread(target=self._read_up, name="chaos-up-output", daemon=True).start()
        self._wait(lambda: bool(self.state().get("children")), 240, "the roles to start")
        self.watcher = Watcher(self.run, self.state(), self.obs)
        n_roles = len(self.state()["children"])
        self._wait(lambda: len(self.latest()) == n_roles and self.actor_version() >= self.profile.warm_version,
                   420, f"all {n_roles} roles up and the actor at version {self.profile.warm_version}")
        self.progress(f"warm: {n_roles} roles, actor at v{self.actor_version()}")

    def faults(self) -> None:
        p = self.profile
        self.loss = UplinkLoss(self.run, p.loss_rack, p.loss)
        self.loss.install()
        self.progress(f"{p.loss:.0%} packet loss on rack {p.loss_rack}'s uplink ({self.loss.port} in {self.loss.ns})")
        schedule = [(t, "rollout") for t in p.rollout_kills_s]
        if p.replicator_kill_s is not None:
            schedule.append((p.replicator_kill_s, "replicator"))
        if p.actor_kill_s is not None:
            schedule.append((p.actor_kill_s, "actor"))
        schedule.sort()
        self.t0 = time.time()
        for at, kind in schedule:
            while time.time() < self.t0 + at:
                self._up_alive()
                time.sleep(0.2)
            self.kill(kind)
        while time.time() < self.t0 + p.faults_s:
            self._up_alive()
            time.sleep(0.5)

    def kill(self, kind: str) -> None:
        children = self.state().get("children", {})
        names = sorted(n for n in children if n.startswith(kind + "-"))
        if kind == "replicator":  # the lossy rack's relay: its subtree repairs across the lossy uplink
            names = [n for n in names if f"r{self.profile.loss_rack}" in n] or names
        if not names:
            raise RuntimeError(f"no live {kind} to kill (children: {sorted(children)})")
        # the least-killed first: the launcher gives up on a role after a few restarts
        times = {n: sum(1 for k in self.kills if k.role == n) for n in names}
        role = self.rng.choice(sorted(n for n in names if times[n] == min(times.values())))
        pid = children[role]
        k = Kill(kind=kind, role=role, pid=pid, at=time.time(), at_rel_s=time.time() - self.t0,
                 actor_version_before=self.actor_version())
        seen = self.latest().get(role)
        # a restarted incarnation killed before it was up has no liveliness token to lose
        k.figures["was_running"] = seen is not None and seen["pid"] == pid
        os.kill(pid, signal.SIGKILL)
        self.kills.append(k)
        self.progress(f"t={k.at_rel_s:5.1f}s kill -9 {role} (pid {pid}), actor at v{k.actor_version_before}")
        t = threading.Thread(target=self._track, args=(k,), name=f"chaos-track-{role}", daemon=True)
        t.start()
        self._trackers.append(t)

    def _track(self, k: Kill, timeout: float = 240.0) -> None:
        """Restart and catch-up of one killed role, polled at 4 Hz."""
        assert self.watcher is not None
        deadline = time.time() + timeout
        new_pid = None
        while time.time() < deadline and new_pid is None:
            pid = self.state().get("children", {}).get(k.role)
            if pid is not None and pid != k.pid:
                new_pid = pid
                k.figures["respawn_s"] = time.time() - k.at
            time.sleep(0.1)
        while time.time() < deadline:
            if any(later.role == k.role and later.at > k.at for later in self.kills):
                k.figures["superseded"] = True  # killed again before it recovered
                return
            try:
                st = self.watcher.role(k.role)
                actor = self.watcher.role(self.actor_name()) if k.kind != "actor" else st
            except Exception:
                st = actor = None
            if st is not None and st["pid"] == new_pid:
                if "status_s" not in k.figures:
                    k.figures["status_s"] = time.time() - k.at
                if k.kind == "actor":
                    if (st["published_version"] or 0) > k.actor_version_before:
                        k.figures["latest_weights_s"] = time.time() - k.at
                        k.figures["first_new_version"] = st["published_version"]
                        return
                elif actor is not None and st["held_version"] is not None and \
                        st["held_version"] >= (actor["published_version"] or 0) >= 0:
                    k.figures["latest_weights_s"] = time.time() - k.at
                    k.figures["caught_up_version"] = st["held_version"]
                    return
            time.sleep(0.25)

    def actor_name(self) -> str:
        return next(n for n in self.state().get("children", {}) if n.startswith("actor-")) if self.state() else ""

    def settle(self) -> dict[str, Any]:
        """Wait for the trackers, then for one status round in which every live replica holds the
        actor's published version with the actor's checksum."""
        deadline = time.time() + self.profile.settle_s
        for t in self._trackers:
            t.join(timeout=max(1.0, deadline - time.time()))
        assert self.watcher is not None
        best: dict[str, Any] = {}
        while True:
            snap = self.watcher.round(timeout=2.0)
            actors = [s for s in snap.values() if s["kind"] == "actor"]
            if actors:
                a = actors[0]
                replicas = {n: s for n, s in snap.items() if s["kind"] in ("rollout", "replicator")}
                same = {n: s["held_version"] == a["published_version"] and s["held_checksum"] == a["published_checksum"]
                        for n, s in replicas.items()}
                check = {"actor_version": a["published_version"], "actor_checksum": a["published_checksum"],
                         "replicas": len(replicas), "identical": sum(same.values()),
                         "differing": {n: [replicas[n]["held_version"], replicas[n]["held_checksum"]]
                                       for n, ok in same.items() if not ok}}
                if not best or check["identical"] >= best["identical"]:
                    best = check
                if replicas and all(same.values()) and len(replicas) == self.expected_replicas():
                    best["all_identical"] = True
                    return best
            if time.time() > deadline:
                best["all_identical"] = False
                return best
            time.sleep(0.2)

    def expected_replicas(self) -> int:
        return len([n for n in self.state().get("children", {}) if n.startswith(("rollout-", "replicator-"))])

    def stop(self) -> dict[str, Any]:
        assert self.up is not None
        self.progress("stopping the run (SIGINT)")
        self.up.send_signal(signal.SIGINT)
        try:
            self.up.wait(timeout=240)
        except subprocess.TimeoutExpired:
            self.up.kill()
            self.up.wait()
        try:
            return json.loads((self.run_dir / "result.json").read_text())
        except (OSError, ValueError):
            return {}

    def cleanup(self) -> None:
        if self.loss is not None:
            try:
                self.loss.remove()
            except Exception:
                pass
        if self.watcher is not None:
            try:
                self.watcher.close()
            except Exception:
                pass
            self.watcher = None
        if self.up is not None and self.up.poll() is None:
            self.up.send_signal(signal.SIGINT)
            try:
                self.up.wait(timeout=120)
            except subprocess.TimeoutExpired:
                self.up.kill()
                self.up.wait()


# ----------------------------------------------------------------------------------------------
# Figures and checks


def detection(k: Kill, obs: Observations) -> None:
    """Liveliness and launcher detection times of one kill, from what was observed."""
    gone = next((t for t, r, a in obs.alive if r == k.role and not a and t >= k.at), None)
    back = next((t for t, r, a in obs.alive if r == k.role and a and gone is not None and t > gone), None)
    crashed = next((t for t, line in obs.lines if t >= k.at and f"{k.role} crashed" in line), None)
    k.figures["detect_liveliness_s"] = None if gone is None else gone - k.at
    k.figures["detect_launcher_s"] = None if crashed is None else crashed - k.at
    k.figures["rejoin_s"] = None if back is None else back - k.at


def version_monotonic(samples: list[tuple[float, dict[str, dict[str, Any]]]]) -> dict[str, Any]:
    """Per role incarnation (name, pid): policy versions never go down; the actor's published
    version never goes down at all, across its restarts."""
    seen: dict[tuple[str, int], int] = {}
    published = -1
    regressions = []
    for t, snap in samples:
        for name, s in snap.items():
            v = int(s["policy_version"])
            key = (name, int(s["pid"]))
            if v >= 0 and v < seen.get(key, -1):
                regressions.append(f"{name} pid {s['pid']}: v{seen[key]} -> v{v}")
            if v >= 0:
                seen[key] = max(v, seen.get(key, -1))
            if s["kind"] == "actor" and s["published_version"] is not None:
                pv = int(s["published_version"])
                if pv < published:
                    regressions.append(f"{name} published v{published} -> v{pv}")
                published = max(published, pv)
    return {"monotonic": not regressions, "regressions": regressions[:20], "incarnations_seen": len(seen)}


#: how long after a fault the actor must have published past its version at the fault
RECOVERY_S = 90.0


def learning(kills: list[Kill], evals: list[dict[str, Any]], samples: list[tuple[float, dict]], t0: float,
             t_end: float) -> dict[str, Any]:
    """Versions after each fault, and eval return before the faults, between them and after."""
    def actor_v(t: float) -> int:
        vs = [max((int(s["published_version"] or 0) for s in snap.values() if s["kind"] == "actor"), default=-1)
              for ts, snap in samples if ts <= t]
        return max(vs, default=-1)

    per_fault = []
    for i, k in enumerate(kills):
        # by the next fault, or RECOVERY_S after this one when the next comes sooner (faults
        # overlap: a restart takes tens of seconds on a loaded machine), or by the end
        nxt = kills[i + 1].at if i + 1 < len(kills) else t_end
        until = min(t_end, max(nxt, k.at + RECOVERY_S))
        per_fault.append({"role": k.role, "version_at_kill": k.actor_version_before, "version_by": actor_v(until),
                          "within_s": round(until - k.at, 1), "learned_on": actor_v(until) > k.actor_version_before})
    first_kill = kills[0].at if kills else t0
    before = [e["return_mean"] for e in evals if e["time"] < first_kill]
    after_last = [e["return_mean"] for e in evals if kills and e["time"] >= kills[-1].at]
    mean = (lambda xs: sum(xs) / len(xs) if xs else None)
    return {
        "per_fault": per_fault,
        "learned_after_every_fault": all(f["learned_on"] for f in per_fault),
        "eval_return_before_faults": mean(before[-3:]),
        "eval_return_after_last_fault": mean(after_last[-3:]),
        "evals": [{"t_s": round(e["time"] - t0, 1), "version": e["version"], "return_mean": round(e["return_mean"], 2),
                   "success_once": e["success_once"]} for e in evals],
    }


def summarize(kills: list[Kill]) -> dict[str, Any]:
    """Per role kind: mean and max of each figure over its kills."""
    out: dict[str, Any] = {}
    for kind in ("rollout", "replicator", "actor"):
        ks = [k for k in kills if k.kind == kind]
        if not ks:
            continue
        row: dict[str, Any] = {"kills": len(ks)}
        for f in ("detect_liveliness_s", "detect_launcher_s", "respawn_s", "rejoin_s", "status_s", "latest_weights_s"):
            vals = [k.figures.get(f) for k in ks if k.figures.get(f) is not None]
            row[f] = {"mean": sum(vals) / len(vals), "max": max(vals), "n": len(vals)} if vals else None
        out[kind] = row
    return out


def run_chaos(topology: Path, profile: Profile, runs_root: Path | None = None, base_port: int | None = None,
              progress: Callable[[str], None] = lambda m: None) -> dict[str, Any]:
    why = iptables_usable()
    if why is not None:
        raise RuntimeError(f"chaos: {why}")
    t_start = time.time()
    tmp = None
    if runs_root is None:
        tmp = tempfile.mkdtemp(prefix="dvla-chaos-")
        runs_root = Path(tmp)
    cr = ChaosRun(topology, profile, runs_root.resolve(), base_port, progress)
    try:
        cr.start()
        cr.faults()
        identical = cr.settle()
        t_end = time.time()
        dropped_packets = cr.loss.dropped_packets() if cr.loss else 0
        cr.loss.remove() if cr.loss else None
        assert cr.watcher is not None
        cr.watcher.close()
        cr.watcher = None
        result = cr.stop()
        for k in cr.kills:
            detection(k, cr.obs)
        acct = result.get("accounting", {})
        from dvla.ledger import read_counters

        # a killed rollout incarnation that produced anything must be listed with its loss (one
        # killed while still starting has produced nothing, possibly not even its counter file)
        produced = {(d["role"], d["pid"]): d.get("produced", 0) for d in read_counters(cr.run_dir)
                    if d.get("kind") == "rollout"}
        killed_rollouts = {(k.role, k.pid) for k in cr.kills if k.kind == "rollout" and produced.get((k.role, k.pid), 0)}
        lost_rollouts = {(x["role"], x["pid"]) for x in acct.get("lost_by_incarnation", []) if x["where"] == "rollout"}
        doc = {
            "profile": dataclasses.asdict(profile),
            "run": cr.run,
            "topology": str(topology),
            "kills": [{"kind": k.kind, "role": k.role, "pid": k.pid, "at_s": round(k.at_rel_s, 1),
                       **{f: (round(v, 3) if isinstance(v, float) else v) for f, v in k.figures.items()}}
                      for k in cr.kills],
            "figures": summarize(cr.kills),
            "packet_loss": {"rack": profile.loss_rack, "probability": profile.loss, "dropped_packets": dropped_packets},
            "replicas": identical,
            "versions": version_monotonic(cr.obs.samples),
            "learning": learning(cr.kills, cr.obs.evals, cr.obs.samples, cr.t0, t_end),
            "accounting": acct,
            "every_killed_rollout_accounted": killed_rollouts <= lost_rollouts,
            "restarts": result.get("restarts"),
            "exit_code": cr.up.returncode if cr.up else None,
            "elapsed_s": time.time() - t_start,
        }
        doc["ok"] = bool(
            identical.get("all_identical") and doc["versions"]["monotonic"] and acct.get("unaccounted") == 0
            and acct.get("lost_within_bounds") and doc["every_killed_rollout_accounted"]
            and doc["learning"]["learned_after_every_fault"] and dropped_packets > 0
            and all(k.figures.get("latest_weights_s") is not None or k.figures.get("superseded") for k in cr.kills)
        )
        return doc
    finally:
        cr.cleanup()
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def format_table(doc: dict[str, Any]) -> str:
    def f(x: Any) -> str:
        return "-" if x is None else f"{x['mean']:.2f} / {x['max']:.2f}"

    lines = [f"chaos ({doc['profile']['name']}): {len(doc['kills'])} kills, "
             f"{doc['packet_loss']['probability']:.0%} loss on rack {doc['packet_loss']['rack']} "
             f"({doc['packet_loss']['dropped_packets']} packets dropped)",
             f"{'kind':<11}{'kills':>6}  {'detect (liveliness)':>20}{'detect (launcher)':>19}{'respawn':>15}"
             f"{'rejoin':>15}{'latest weights':>17}   (s, mean / max)"]
    for kind, row in doc["figures"].items():
        lines.append(f"{kind:<11}{row['kills']:>6}  {f(row['detect_liveliness_s']):>20}{f(row['detect_launcher_s']):>19}"
                     f"{f(row['respawn_s']):>15}{f(row['rejoin_s']):>15}{f(row['latest_weights_s']):>17}")
    a = doc["accounting"]
    lines.append(f"accounting: produced {a.get('produced')} = consumed {a.get('consumed')} + dropped {a.get('dropped')}"
                 f" + rejected {a.get('rejected')} + lost {a.get('lost')}; unaccounted {a.get('unaccounted')}, "
                 f"lost within bounds: {a.get('lost_within_bounds')}")
    r, v, lrn = doc["replicas"], doc["versions"], doc["learning"]
    lines.append(f"replicas identical to the actor's v{r.get('actor_version')}: {r.get('identical')}/{r.get('replicas')}; "
                 f"versions monotonic: {v['monotonic']}; learned on after every fault: {lrn['learned_after_every_fault']}")
    lines.append(f"eval return: {lrn['eval_return_before_faults']} before the first kill -> "
                 f"{lrn['eval_return_after_last_fault']} after the last one ({len(lrn['evals'])} evals)")
    lines.append("OK" if doc["ok"] else "FAILED")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.chaos", description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, required=True, help="write the results (JSON) here")
    ap.add_argument("--quick", action="store_true", help="the short profile (one fault of each kind)")
    ap.add_argument("--topology", type=Path, default=ROOT / "topologies" / "8node.yaml")
    ap.add_argument("--runs", type=Path, default=None, help="keep the run directory here")
    ap.add_argument("--base-port", type=int, default=None)
    args = ap.parse_args(argv)
    profile = QUICK if args.quick else FULL
    try:
        doc = run_chaos(args.topology, profile, args.runs, args.base_port,
                        progress=lambda m: print(f"[chaos] {m}", file=sys.stderr, flush=True))
    except RuntimeError as err:
        print(f"chaos: {err}", file=sys.stderr)
        return 2
    doc["command"] = "python -m benchmarks.chaos " + " ".join(argv if argv is not None else sys.argv[1:])
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(doc, indent=1, default=str))
    print(format_table(doc))
    print(f"wrote {args.json}  ({doc['elapsed_s']:.0f} s)")
    return 0 if doc["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())

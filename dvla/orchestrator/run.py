"""`dvla up`: prepare the run directory, start every role, watch, stop in order, report.

Stop order matters for the accounting identity: rollouts and evaluators first (they flush their
last chunks), then the actor (which counts what it never learned from) with the replicators.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ..config import BudgetConfig, Topology
from ..fabric import Fabric, load_secret, new_secret, plane_config
from ..fabric.messages import Command
from .launcher import Launcher, log_tail
from .monitor import Monitor
from .plan import Plan, is_local_host, make_plan, pinning_problems
from .topology import dump_topology_yaml

log = logging.getLogger("dvla.up")


class ExitCode:
    SUCCESS = 0  # stop condition reached (and the success target, when one was set)
    TARGET_MISSED = 1  # budget ran out before the success target
    ROLE_FAILED = 2  # a role kept crashing, or the cluster could not start
    INTERRUPTED = 130  # Ctrl-C / dvla down


@dataclass(frozen=True, kw_only=True)
class UpOptions:
    """Command-line overrides of `dvla up`."""

    #: override task.budget.max_env_steps
    max_env_steps: int | None = None
    #: override task.budget.until_success
    until_success: float | None = None
    #: override task.budget.max_wall_s
    max_wall_s: float | None = None
    #: "async" or "sync" (overrides the topology's mode)
    mode: str | None = None
    #: override the topology's master seed
    seed: int | None = None
    #: first port to hand out (None: the topology's base_port)
    base_port: int | None = None
    #: runs/ directory
    runs_root: Path = Path("runs")
    #: seconds between status collections
    poll_s: float = 1.0
    #: restarts allowed per role
    max_restarts: int = 3


def apply_overrides(topo: Topology, opts: UpOptions) -> Topology:
    b = topo.task.budget
    budget = BudgetConfig(
        max_env_steps=opts.max_env_steps if opts.max_env_steps is not None else b.max_env_steps,
        until_success=opts.until_success if opts.until_success is not None else b.until_success,
        consecutive=b.consecutive,
        max_wall_s=opts.max_wall_s if opts.max_wall_s is not None else b.max_wall_s,
    )
    task = dataclasses.replace(topo.task, budget=budget)
    seed = opts.seed if opts.seed is not None else topo.seed
    return dataclasses.replace(topo, task=task, mode=opts.mode or topo.mode, seed=seed)  # type: ignore[arg-type]


def prepare_run_dir(root: Path, run: str) -> Path:
    """runs/<run>/, emptied of a previous run's files (refuses while that run is alive)."""
    run_dir = (root / run).resolve()
    state = run_dir / "state.json"
    if state.exists():
        try:
            pid = json.loads(state.read_text()).get("pid")
        except (OSError, ValueError):
            pid = None
        if pid and _pid_alive(pid) and pid != os.getpid():
            raise RuntimeError(f"run {run!r} is already up (pid {pid}); `dvla down {run}` first")
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    return run_dir


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
        return True
    except (ProcessLookupError, PermissionError):
        return False


def resolve_secret(topo: Topology, run_dir: Path) -> tuple[str, str]:
    """(hex secret, where it came from); a fresh per-run secret unless one is configured."""
    if topo.secret_file:
        return load_secret(topo.secret_file).hex(), topo.secret_file
    if os.environ.get("DVLA_SECRET"):
        return load_secret(None).hex(), "DVLA_SECRET"
    secret = new_secret()
    path = run_dir / "secret"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(secret)
    return secret, str(path)


def ctrl_tls(topo: Topology) -> Any:
    """The TLS files a tool needs to reach the ctrl plane (None when it is plain TCP)."""
    return topo.tls if topo.tls is not None and "ctrl" in topo.tls.planes else None


def ctrl_tls_dict(topo: Topology) -> dict[str, Any] | None:
    tls = ctrl_tls(topo)
    return None if tls is None else {"root_ca": tls.root_ca, "cert": tls.cert, "key": tls.key, "mtls": tls.mtls}


def tool_fabric(run: str, entry: tuple[str, ...], secret: bytes, name: str = "orchestrator", tls: Any = None,
                open_timeout_s: float = 60.0) -> Fabric:
    """A client-only fabric for tools (orchestrator, `dvla status`) on the ctrl plane (`tls`: the
    topology's TLS files when the ctrl plane uses TLS). Opening retries until `open_timeout_s`:
    the router's listener accepts connections by then (the launcher waited for it), but opening
    a session on a machine loaded by every role's start-up can take many seconds."""
    conf = plane_config(mode="client", connect=entry, tls=tls)
    return Fabric(run=run, name=name, ctrl_conf=conf, data_conf=None, secret=secret, open_timeout_s=open_timeout_s)


class Up:
    """One `dvla up` from start to exit code."""

    def __init__(self, topo: Topology, opts: UpOptions, on_tick: Callable[["Up"], None] | None = None) -> None:
        self.topo = apply_overrides(topo, opts)
        self.opts = opts
        self.on_tick = on_tick
        pinning = pinning_problems(self.topo)
        if pinning:  # caught before anything is created, not as a role that dies on start
            raise ValueError("\n".join(f"{self.topo.source}: {p}" for p in pinning))
        self.run_dir = prepare_run_dir(opts.runs_root, self.topo.run)
        self.plan: Plan = make_plan(self.topo, str(self.run_dir), opts.base_port)
        self.secret, self.secret_source = resolve_secret(self.topo, self.run_dir)
        self.events: list[str] = []
        self.reason: str | None = None
        self.monitor: Monitor | None = None
        self._interrupted = threading.Event()
        self.netns = None
        env = dict(os.environ)
        env["DVLA_SECRET"] = self.secret
        env.setdefault("PYTHONUNBUFFERED", "1")
        env.setdefault("OMP_NUM_THREADS", "1")
        self.launcher = Launcher(self.run_dir, env, max_restarts=opts.max_restarts)

    def interrupt(self) -> None:
        self._interrupted.set()

    def _write_state(self) -> None:
        state = {
            "run": self.topo.run,
            "pid": os.getpid(),
            "ctrl_entry": list(self.plan.ctrl_entry),
            "ctrl_tls": ctrl_tls_dict(self.topo),
            "secret_file": self.secret_source if self.secret_source != "DVLA_SECRET" else None,
            "children": self.launcher.pids(),
            "restarts": {n: c.restarts for n, c in self.launcher.children.items()},
            "netns": self.netns.names() if self.netns else [],
            "remote": {p.config.name: p.host for p in self.plan.processes if not is_local_host(p.host)},
            "started": time.time(),
        }
        tmp = self.run_dir / "state.json.tmp"
        tmp.write_text(json.dumps(state, indent=1))
        tmp.replace(self.run_dir / "state.json")

    def run(self) -> int:
        (self.run_dir / "topology.yaml").write_text(dump_topology_yaml(self.topo))
        for w in self.plan.warnings:
            self.events.append(f"warning: {w}")
        if self.topo.emulate == "netns":
            from .netns import NetnsCluster

            self.netns = NetnsCluster(self.topo, self.plan)
            self.netns.create()
            self.launcher.wrap = self.netns.wrapper()
        if any(not is_local_host(p.host) for p in self.plan.processes):
            from .ssh import SshWrapper

            ssh = SshWrapper(self.topo, self.secret, self.launcher.env, local=self.launcher.wrap)
            ssh.check_all()  # one clear line naming the host, before anything starts
            self.launcher.wrap = ssh
        try:
            for p in self.plan.processes:
                self.launcher.add(p)
            self.launcher.start_all()
            self._write_state()
            fabric = tool_fabric(self.topo.run, self.plan.ctrl_entry, bytes.fromhex(self.secret),
                                 tls=ctrl_tls(self.topo))
            try:
                self.monitor = Monitor(fabric, self.run_dir, self.topo.task.budget)
                code = self._watch(fabric)
                self._shutdown(fabric)
            finally:
                if self.monitor is not None:
                    self.monitor.close()
                fabric.close()
            self._report(code)
            return code
        finally:
            self.launcher.kill_all()
            if self.netns is not None:
                self.netns.destroy()
            state = self.run_dir / "state.json"
            if state.exists():
                state.unlink()

    def _watch(self, fabric: Fabric) -> int:
        assert self.monitor is not None
        while True:
            if self._interrupted.is_set():
                self.reason = "interrupted"
                return ExitCode.INTERRUPTED
            events = self.launcher.poll(stopping=False)
            self.events.extend(events)
            if any(s.failed for s in self.launcher.children.values()):
                failed = [s for s in self.launcher.children.values() if s.failed]
                self.reason = "role_failed:" + ",".join(s.name for s in failed)
                for s in failed:
                    self.events.append(f"{s.name} last log lines:\n" + log_tail(s.log_path, 15, indent="  "))
                return ExitCode.ROLE_FAILED
            if events:
                self._write_state()
            self.monitor.collect()
            if self.on_tick is not None:
                self.on_tick(self)
            reason = self.monitor.stop_reason()
            if reason is not None:
                self.reason = reason
                b = self.topo.task.budget
                if b.until_success is not None and not self.monitor.success_reached():
                    return ExitCode.TARGET_MISSED
                return ExitCode.SUCCESS
            self._interrupted.wait(self.opts.poll_s)

    def _shutdown(self, fabric: Fabric) -> None:
        """Stop leaves first (they flush their last chunks), then the actor and the relays
        together (the tools' ctrl link runs through the actor's router, so relays are told
        while it is still up); escalate to signals on timeout."""
        groups = [("rollout", "evaluator"), ("actor", "replicator")]
        for kinds in groups:
            names = [n for n, s in self.launcher.children.items() if s.proc.config.kind in kinds and s.alive()]
            for n in names:
                fabric.publish_ctrl(fabric.keys.cmd(n), Command(target=n, verb="stop", args={}, issued_ns=time.time_ns()))
            left = self.launcher.wait_exit(names, timeout=15.0)
            if left:
                self.events.append(f"no clean exit from {', '.join(left)}: terminating")
                self.launcher.stop(left, timeout=5.0)
        self.launcher.poll(stopping=True)

    def _accounting(self) -> dict[str, Any]:
        """Exact across kills from the counter files when every role ran on this host (remote
        roles write theirs on their own host); from the clean-exit summaries otherwise."""
        if all(is_local_host(p.host) for p in self.plan.processes):
            acct = accounting_from_counters(self.run_dir)
            if acct is not None:
                return acct
        return accounting_from_summaries(self.run_dir)

    def _report(self, code: int) -> None:
        assert self.monitor is not None
        res = self.monitor.result()
        res.update(
            {
                "run": self.topo.run,
                "reason": self.reason,
                "exit_code": code,
                "restarts": {n: s.restarts for n, s in self.launcher.children.items()},
                "accounting": self._accounting(),
            }
        )
        (self.run_dir / "result.json").write_text(json.dumps(res, indent=1, default=str))
        try:
            from .plots import plot_run

            plot_run(self.run_dir)
        except Exception as err:  # a missing plot must not hide the run's result
            self.events.append(f"plot failed: {err}")


def accounting_from_summaries(run_dir: Path) -> dict[str, Any]:
    """produced = consumed + dropped + rejected + unaccounted, from the roles' final summaries."""
    produced = consumed = dropped = rejected = 0
    for path in sorted((run_dir / "summaries").glob("*.json")):
        doc = json.loads(path.read_text())
        if doc["kind"] == "rollout":
            produced += int(doc["extra"].get("chunks_produced", 0))
        elif doc["kind"] == "actor":
            data = doc["planes"].get("data", {})
            consumed += int(data.get("consumed", 0))
            dropped += int(data.get("dropped", 0))
            rejected += int(data.get("rejected", 0))
    return {
        "produced": produced,
        "consumed": consumed,
        "dropped": dropped,
        "rejected": rejected,
        "unaccounted": produced - consumed - dropped - rejected,
    }


#: bytes a killed sender's Zenoh may hold unsent: the data priority's tx queue (2 batches, Zenoh's
#: default) plus the batch being filled, of at most 64 KiB each
ZENOH_TX_BYTES = 3 * 65535


def _tcp_buffer_max(name: str) -> int:
    """The kernel's largest TCP buffer of one direction (net.ipv4.tcp_rmem / tcp_wmem, third field)."""
    try:
        return int(Path(f"/proc/sys/net/ipv4/{name}").read_text().split()[2])
    except (OSError, ValueError, IndexError):
        return 6 << 20


def accounting_from_counters(run_dir: Path) -> dict[str, Any] | None:
    """produced = consumed + dropped + rejected + lost, exactly, across kills (None without counter files).

    Every rollout and actor incarnation leaves a counter file (dvla/roles/counters.py) even when
    killed. `lost` lists, per killed incarnation, the chunks that died with it and the bound its
    in-flight window puts on them: for a rollout its ship queue (+ the chunk being shipped) and
    what its Zenoh had not sent yet; for the actor its slots and inbox, plus
    what was in the live rollouts' Zenoh queues and the TCP buffers of their links when it died.
    A missing chunk that no kill explains is `unaccounted`.
    """
    from ..roles.counters import read_counters

    docs = read_counters(run_dir)
    rollouts = [d for d in docs if d.get("kind") == "rollout"]
    actors = [d for d in docs if d.get("kind") == "actor"]
    if not rollouts and not actors:
        return None
    consumed = 0
    dropped: dict[str, int] = {}
    rejected: dict[str, int] = {}
    got: dict[str, int] = {}  # rollout incarnation -> chunks that left some actor's inbox
    fabric_bp: dict[str, int] = {}  # rollout name -> the fabric's backpressure drops
    fabric_rej: dict[str, int] = {}  # rollout name -> chunks the fabric could not decode
    lost: list[dict[str, Any]] = []
    ranges: dict[str, list[tuple[int, int, int, int]]] = {}  # rollout incarnation -> (actor inc, first, last, got)
    killed_actors: dict[int, dict[str, Any]] = {}
    notes: list[str] = []
    unaccounted = 0

    def bump(d: dict[str, int], k: str, n: int) -> None:
        if n:
            d[k] = d.get(k, 0) + n

    for a in actors:
        held = 0
        own_rej: dict[str, int] = {}
        for src, c in a.get("sources", {}).items():
            got[src] = got.get(src, 0) + c["got"]
            ranges.setdefault(src, []).append((a["incarnation"], c["first"], c["last"], c["got"]))
            settled = 0
            for k, v in c.items():
                if k == "consumed":
                    consumed += v
                elif k.startswith("dropped."):
                    bump(dropped, k[len("dropped."):], v)
                elif k.startswith("rejected."):
                    bump(rejected, k[len("rejected."):], v)
                    bump(own_rej, src.rsplit("#", 1)[0], v)
                else:
                    continue
                settled += v
            held += c["got"] - settled
        for peer, f in a.get("fabric", {}).items():
            bump(fabric_bp, peer, f.get("backpressure", 0))
            bump(fabric_rej, peer, f.get("rejected", 0) - own_rej.get(peer, 0))
        if a.get("clean"):
            if held:
                unaccounted += held
                notes.append(f"{a['file']}: {held} chunks held at a clean exit")
        else:
            killed_actors[a["incarnation"]] = {
                "role": a["role"], "incarnation": a["incarnation"], "pid": a["pid"], "where": "actor",
                "died_ns": a["updated_ns"], "lost": held, "in_actor": held, "in_transit": 0,
                "lost_bound": a["slots"] + 2 + a["inbox_cap"], "_transit_bound": 0}
            lost.append(killed_actors[a["incarnation"]])

    produced = sum(r.get("produced", 0) for r in rollouts)
    foreign = 0
    window = ZENOH_TX_BYTES + _tcp_buffer_max("tcp_wmem") + _tcp_buffer_max("tcp_rmem")
    by_name: dict[str, list[dict[str, Any]]] = {}
    for r in rollouts:
        by_name.setdefault(r["role"], []).append(r)
    shipped_all = sum(r.get("shipped", 0) for r in rollouts)
    # a rollout killed before it shipped anything: size its window with the run's mean chunk
    mean_bytes = sum(r.get("bytes", 0) for r in rollouts) / shipped_all if shipped_all else 1.0
    for name, incs in sorted(by_name.items()):
        # Where each incarnation's missing chunks are, from the seq ranges every actor
        # incarnation received: inside one actor's range (the fabric dropped or could not decode
        # them), between two actor incarnations (died with the first), or after the last one
        # received (died with the rollout, or with the actor at the end).
        parts = {r["incarnation"]: _missing_parts(r, ranges.get(f"{name}#{r['incarnation']}", [])) for r in incs}
        bp, rej = fabric_bp.get(name, 0), fabric_rej.get(name, 0)
        inner = sum(max(0, pt["inner"]) for pt in parts.values())
        use_bp = min(bp, inner)
        use_rej = min(rej, inner - use_bp)
        bump(dropped, "backpressure", use_bp)
        bump(rejected, "undecodable", use_rej)
        foreign += bp + rej - use_bp - use_rej  # rejects beyond what is missing were never produced: forged
        explain = use_bp + use_rej
        for r in incs:
            pt = parts[r["incarnation"]]
            take = max(0, min(explain, pt["inner"]))
            pt["inner"] -= take
            explain -= take
            chunk_bytes = r.get("bytes", 0) / r["shipped"] if r.get("shipped") else mean_bytes
            if pt["inner"]:
                unaccounted += pt["inner"]
                notes.append(f"{r['file']}: {pt['inner']} chunks missing mid-stream")
            for a, n in pt["between"]:  # died with actor incarnation `a` (or in its absence)
                if n and a in killed_actors:
                    k = killed_actors[a]
                    k["lost"] += n
                    k["in_transit"] += n
                    k["_transit_bound"] += -(-window // max(1, int(chunk_bytes))) + 1
                elif n:
                    unaccounted += n
                    notes.append(f"{r['file']}: {n} chunks missing across a clean actor restart")
            tail, last_actor = pt["tail"], pt["last_actor"]
            if not r.get("clean"):
                in_queue = r.get("produced", 0) - r.get("shipped", 0)
                lost.append({"role": name, "incarnation": r["incarnation"], "pid": r["pid"], "where": "rollout",
                             "died_ns": r["updated_ns"], "lost": tail, "in_queue": in_queue, "in_transit": tail - in_queue,
                             "lost_bound": r.get("queue_cap", 0) + 1 + -(-ZENOH_TX_BYTES // max(1, int(chunk_bytes))) + 1})
            elif tail and last_actor in killed_actors and killed_actors[last_actor]["died_ns"] >= r["updated_ns"] - 10**9:
                k = killed_actors[last_actor]
                k["lost"] += tail
                k["in_transit"] += tail
            elif tail:
                unaccounted += tail
                notes.append(f"{r['file']}: {tail} chunks missing at the end of a clean incarnation")
    for peer in set(fabric_bp) | set(fabric_rej):  # traffic under names no rollout ever had
        if peer not in by_name:
            foreign += fabric_bp.get(peer, 0) + fabric_rej.get(peer, 0)
    for a in lost:
        if a["where"] == "actor":
            a["lost_bound"] += a.pop("_transit_bound")
    total_lost = sum(x["lost"] for x in lost)
    total_dropped = sum(dropped.values())
    total_rejected = sum(rejected.values())
    residual = produced - consumed - total_dropped - total_rejected - total_lost
    if residual != unaccounted:  # the two ways of counting must agree; say so if they do not
        notes.append(f"identity residual {residual} != {unaccounted} chunks found missing or held")
    return {
        "produced": produced,
        "consumed": consumed,
        "dropped": total_dropped,
        "dropped_by_reason": dropped,
        "rejected": total_rejected,
        "rejected_by_reason": rejected,
        "lost": total_lost,
        "lost_by_incarnation": sorted(lost, key=lambda x: x["died_ns"]),
        "lost_within_bounds": all(0 <= x["lost"] <= x["lost_bound"] for x in lost),
        "foreign_rejected": foreign,
        "unaccounted": residual,
        "notes": notes,
        "incarnations": {"rollout": len(rollouts), "actor": len(actors)},
    }


def _missing_parts(r: dict[str, Any], ranges: list[tuple[int, int, int, int]]) -> dict[str, Any]:
    """Split a rollout incarnation's missing chunks (produced - received) by where they went
    missing, from the seq ranges (actor incarnation, first, last, got) the actors received."""
    produced = r.get("produced", 0)
    ranges = sorted(ranges)
    if not ranges:
        return {"inner": 0, "between": [], "tail": produced, "last_actor": None}
    inner = sum(last - first + 1 - n for _a, first, last, n in ranges)
    # chunks before the first receipt went missing in the absence of an actor: count them with
    # the first actor incarnation's predecessor (the one that died), else as mid-stream
    between = []
    head = ranges[0][1]
    if head:
        between.append((ranges[0][0] - 1, head))
    for (a, _f, last, _n), (_b, first, _l, _m) in zip(ranges, ranges[1:]):
        between.append((a, first - last - 1))
    tail = produced - 1 - ranges[-1][2]
    return {"inner": inner, "between": between, "tail": tail, "last_actor": ranges[-1][0]}


def install_sigint(up: Up) -> None:
    def _handler(_signum: int, _frame: Any) -> None:
        up.interrupt()

    signal.signal(signal.SIGINT, _handler)
    signal.signal(signal.SIGTERM, _handler)


# ----------------------------------------------------------------------------------------------
# `dvla up --detach`

#: the detached orchestrator's own output, in the run directory
ORCHESTRATOR_LOG = "orchestrator.log"
#: how long `dvla up --detach` waits for the roles to be started before giving up on the run
DETACH_START_TIMEOUT_S = 180.0


def start_detached(up: Up, body: Callable[[], int]) -> int | None:
    """Run `body` (which runs `up`) in a daemon: double fork, new session, stdin from /dev/null,
    output to RUN_DIR/orchestrator.log. Returns in the caller once the roles are started (the run's
    state.json exists) with the daemon's pid, or None if it exited first."""
    log_path = up.run_dir / ORCHESTRATOR_LOG
    read_end, write_end = os.pipe()
    first = os.fork()
    if first == 0:  # first child: leave the terminal's session, fork the daemon, exit
        os.close(read_end)
        code = ExitCode.ROLE_FAILED
        try:
            os.setsid()
            if os.fork() != 0:
                os._exit(0)
            os.write(write_end, str(os.getpid()).encode())
            os.close(write_end)
            _redirect_std(log_path)
            install_sigint(up)
            code = body()
        except BaseException:  # anything at all: report it in the log, never return into the CLI
            import traceback

            traceback.print_exc()
        finally:
            try:
                sys.stdout.flush()
                sys.stderr.flush()
            finally:
                os._exit(code)
    os.close(write_end)
    with os.fdopen(read_end, "rb") as pipe:
        text = pipe.read().decode()
    os.waitpid(first, 0)
    if not text.strip().isdigit():
        return None
    pid = int(text)
    state = up.run_dir / "state.json"
    deadline = time.monotonic() + DETACH_START_TIMEOUT_S
    while time.monotonic() < deadline:
        if state.exists():
            return pid
        if not _pid_alive(pid) or _zombie(pid):
            return None
        time.sleep(0.1)
    return pid  # still starting (e.g. a slow netns build): it is running, the log says more


def _redirect_std(log_path: Path) -> None:
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)
    os.close(devnull)
    out = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(out, 1)
    os.dup2(out, 2)
    os.close(out)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def _zombie(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[-1].split()[0] == "Z"
    except OSError:
        return False

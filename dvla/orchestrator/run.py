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
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ..config import TlsConfig, Topology
from ..fabric import Fabric, TlsFiles, load_secret, new_secret, plane_config
from ..fabric.identity import Identity, IdentityError
from ..fabric.messages import Command
from ..ledger import reconcile
from .launcher import Launcher, busy_ports, log_tail
from .evaljoin import EvalJoin
from .monitor import Monitor
from .netns import NetnsCluster, NetnsWrapper
from .plan import make_plan, pinning_problems
from .plots import plot_run
from .process import Plan, is_local_host
from .slurm import SlurmWrapper, slurm_job_for
from .ssh import SshWrapper, write_private
from .topology import dump_topology_yaml
from .wandb_log import WandbLog, missing_wandb
from .zygote import preload_modules

log = logging.getLogger("dvla.up")
#: seconds between status collections
POLL_S = 1.0
#: how long a stopping role may take to exit by itself before it is sent SIGTERM
STOP_WAIT_S = 15.0
#: how often the stop command is sent again to roles that have not exited (a role still
#: starting has no command subscriber yet and misses a single put)
STOP_RESEND_S = 1.0


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
    #: override task.init_weights (a warm start: a safetensors file or a run's checkpoints directory)
    init_weights: str | None = None
    #: first port to hand out (None: the topology's base_port)
    base_port: int | None = None
    #: runs/ directory
    runs_root: Path = Path("runs")
    #: restarts allowed per role (per learner group for the actors)
    max_restarts: int = 3
    #: continue the run in its existing directory (an error when there is nothing to continue)
    resume: bool = False
    #: delete an existing run directory first (checkpoints included) and start over
    fresh: bool = False


def apply_overrides(topo: Topology, opts: UpOptions) -> Topology:
    """The topology with the options that are set (not None) in place of its own values."""

    def given(**values: Any) -> dict[str, Any]:
        return {k: v for k, v in values.items() if v is not None}

    budget = dataclasses.replace(topo.task.budget, **given(max_env_steps=opts.max_env_steps,
                                                           until_success=opts.until_success, max_wall_s=opts.max_wall_s))
    task = dataclasses.replace(topo.task, budget=budget, **given(init_weights=opts.init_weights))
    return dataclasses.replace(topo, task=task, **given(mode=opts.mode, seed=opts.seed))


def prepare_run_dir(root: Path, run: str, resume: bool = False, fresh: bool = False) -> tuple[Path, str | None]:
    """runs/<run>/ and how the run starts in it: (path, None) for a new run, or (path, "...")
    saying what it continues from. An existing directory is continued (its checkpoint resumed,
    its metrics and accounting appended to) and only deleted with `fresh`; refuses while the
    run is alive."""
    run_dir = (root / run).resolve()
    state = run_dir / "state.json"
    if state.exists():
        try:
            pid = json.loads(state.read_text()).get("pid")
        except (OSError, ValueError):
            pid = None
        if pid and pid_alive(pid) and pid != os.getpid():
            raise RuntimeError(f"run {run!r} is already up (pid {pid}); `dvla down {run}` first")
    if resume and fresh:
        raise ValueError("--resume and --fresh exclude each other")
    if fresh and run_dir.exists():
        shutil.rmtree(run_dir)
    manifest = run_dir / "checkpoints" / "MANIFEST.json"
    if resume and not manifest.exists():
        raise RuntimeError(f"--resume: {run_dir} holds no checkpoint (checkpoints/MANIFEST.json) to continue from")
    continued = None
    if manifest.exists():
        try:
            m = json.loads(manifest.read_text())
            continued = f"checkpoint v{m['version']} ({m['env_steps']} env steps, weights {m['checksum']})"
        except (OSError, ValueError, KeyError) as err:
            raise RuntimeError(f"{manifest}: unreadable ({err}); --fresh starts the run over") from err
    elif run_dir.exists() and any(run_dir.iterdir()):
        continued = "no checkpoint yet: the run starts over, its files kept and appended to"
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir, continued


def pid_alive(pid: int) -> bool:
    """Whether process `pid` exists and has not exited (a zombie has)."""
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):
        return False
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except OSError:
        return True


def resolve_secret(topo: Topology, run_dir: Path) -> tuple[str, str]:
    """(hex secret, where it came from); a fresh per-run secret unless one is configured."""
    if topo.secret_file:
        return load_secret(topo.secret_file).hex(), topo.secret_file
    if os.environ.get("DVLA_SECRET"):
        return load_secret(None).hex(), "DVLA_SECRET"
    path = run_dir / "secret"
    if path.exists():  # a continued run keeps its secret
        return load_secret(str(path)).hex(), str(path)
    secret = new_secret()
    write_private(path, secret)
    return secret, str(path)


def resolve_operator(run: str, run_dir: Path) -> tuple[Identity, str]:
    """(the run's operator identity, its file): kept in the run directory (0600), so a
    continued run and the tools (`dvla status`, `dvla stop`) speak as the same operator."""
    path = run_dir / "operator.id"
    if path.exists():
        operator = Identity.from_text(path.read_text(), str(path))
        if operator.run == run:
            return operator, str(path)
    operator = Identity.operator(run)
    write_private(path, operator.to_text())
    return operator, str(path)


def ctrl_tls(topo: Topology) -> TlsConfig | None:
    """The TLS files a tool needs to reach the ctrl plane (None when it is plain TCP)."""
    return topo.tls if topo.tls is not None and "ctrl" in topo.tls.planes else None


def tool_fabric(run: str, entry: tuple[str, ...], secret: bytes, name: str = "orchestrator", tls: Any = None,
                open_timeout_s: float = 60.0, identity: Identity | None = None) -> Fabric:
    """A client-only fabric for tools (orchestrator, `dvla status`) on the ctrl plane (`tls`: the
    topology's TLS files when the ctrl plane uses TLS). Opening retries until `open_timeout_s`:
    the router's listener accepts connections by then (the launcher waited for it), but opening
    a session on a machine loaded by every role's start-up can take many seconds."""
    conf = plane_config(mode="client", connect=entry, tls=tls)
    return Fabric(run=run, name=name, ctrl_conf=conf, data_conf=None, secret=secret, open_timeout_s=open_timeout_s,
                  identity=identity)


def state_fabric(state: dict[str, Any], name: str, entry: tuple[str, ...] | None = None,
                 open_timeout_s: float = 60.0) -> Fabric:
    """A tool's fabric for the live run whose state.json is `state`: its secret, its operator
    identity (commands and status queries need it), its TLS files. Raises ValueError (secret or
    identity unreadable) or ConnectionError."""
    secret = load_secret(state.get("secret_file"))
    identity = None
    if state.get("operator_identity"):
        path = state["operator_identity"]
        try:
            identity = Identity.from_text(Path(path).read_text(), path)
        except OSError as err:
            raise ValueError(f"cannot read the operator identity {path}: {err.strerror or err}") from err
        except IdentityError as err:
            raise ValueError(str(err)) from err
    tls = state.get("ctrl_tls")
    return tool_fabric(state["run"], entry or tuple(state["ctrl_entry"]), secret, name=name,
                       tls=TlsFiles(**tls) if tls else None, identity=identity, open_timeout_s=open_timeout_s)


class Up:
    """One `dvla up` from start to exit code."""

    def __init__(self, topo: Topology, opts: UpOptions, on_tick: Callable[["Up"], None] | None = None) -> None:
        self.topo = apply_overrides(topo, opts)
        self.opts = opts
        self.on_tick = on_tick
        pinning = pinning_problems(self.topo)
        if pinning:  # caught before anything is created, not as a role that dies on start
            raise ValueError("\n".join(f"{self.topo.source}: {p}" for p in pinning))
        no_wandb = missing_wandb(self.topo)
        if no_wandb:
            raise ValueError(no_wandb)
        self.run_dir, self.continued = prepare_run_dir(opts.runs_root, self.topo.run, opts.resume, opts.fresh)
        self.plan: Plan = make_plan(self.topo, str(self.run_dir), opts.base_port)
        busy = busy_ports(list(self.plan.processes))
        if busy:  # else this run's roles would join the planes of whatever listens there
            raise ValueError(f"{self.topo.source}: {busy[0]}")
        self.secret, self.secret_source = resolve_secret(self.topo, self.run_dir)
        self.operator, self.operator_path = resolve_operator(self.topo.run, self.run_dir)
        self.events: list[str] = [f"continuing {self.run_dir}: {self.continued}"] if self.continued else []
        self.reason: str | None = None
        self.monitor: Monitor | None = None
        self._interrupted = threading.Event()
        self.netns: NetnsCluster | None = None
        #: the W&B copy of the scalars (started by run(): its thread must not cross a fork)
        self.wandb: WandbLog | None = None
        env = dict(os.environ)
        env["DVLA_SECRET"] = self.secret
        env.setdefault("PYTHONUNBUFFERED", "1")
        env.setdefault("OMP_NUM_THREADS", "1")
        self.launcher = Launcher(self.run_dir, env, max_restarts=opts.max_restarts, operator=self.operator)
        self.launcher.preload = lambda kinds: preload_modules(kinds, self.topo.task)

    def interrupt(self) -> None:
        self._interrupted.set()

    def _write_state(self) -> None:
        tls = ctrl_tls(self.topo)
        state = {
            "run": self.topo.run,
            "pid": os.getpid(),
            "ctrl_entry": list(self.plan.ctrl_entry),
            # what `dvla status` needs to reach the ctrl plane (fabric.TlsFiles' fields)
            "ctrl_tls": None if tls is None else {"root_ca": tls.root_ca, "cert": tls.cert, "key": tls.key, "mtls": tls.mtls},
            "secret_file": self.secret_source if self.secret_source != "DVLA_SECRET" else None,
            "operator_identity": self.operator_path,
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
            self.netns = NetnsCluster(self.topo, self.plan)
            self.netns.create()
            self.launcher.wrap = NetnsWrapper()
        job = slurm_job_for(self.topo)
        if job is not None:  # every node's roles as steps of the enclosing Slurm job
            slurm = SlurmWrapper(self.topo, self.secret, self.launcher.env, job, self.run_dir, local=self.launcher.wrap)
            slurm.check_all()  # one clear line naming the node, before anything starts
            self.launcher.wrap = slurm
            self.events.append(f"roles start as steps of Slurm job {job.job_id}")
        elif not self._all_local():
            ssh = SshWrapper(self.topo, self.secret, self.launcher.env, local=self.launcher.wrap)
            ssh.check_all()  # one clear line naming the host, before anything starts
            self.launcher.wrap = ssh
        # W&B starts (on its own thread) while the roles start; nothing ever waits on it
        self.wandb = WandbLog.start(self.topo, self.run_dir, len(self.plan.processes))
        try:
            for p in self.plan.processes:
                self.launcher.add(p)
            self.launcher.start_all()
            self._write_state()
            fabric = tool_fabric(self.topo.run, self.plan.ctrl_entry, bytes.fromhex(self.secret),
                                 tls=ctrl_tls(self.topo), identity=self.operator)
            try:
                evaluators = sum(p.config.kind == "evaluator" for p in self.plan.processes)
                self.monitor = Monitor(fabric, self.run_dir, self.topo.task.budget,
                                       EvalJoin(max(1, evaluators), self.topo.task.eval.every_versions),
                                       wandb=self.wandb)
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
            self.launcher.close()
            if self.wandb is not None:  # bounded: finish_timeout_s and a margin
                self.events.extend(self.wandb.close())
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
            failed = [s for s in self.launcher.children.values() if s.failed]
            if failed:
                self.reason = "role_failed:" + ",".join(s.name for s in failed)
                for s in failed:
                    self.events.append(f"{s.name} last log lines:\n" + log_tail(s.log_path, indent="  "))
                return ExitCode.ROLE_FAILED
            if events:
                self._write_state()
            if self.wandb is not None:  # where the W&B run is, or why there is none
                self.events.extend(self.wandb.take_notes())
            self.monitor.collect()
            if self.on_tick is not None:
                self.on_tick(self)
            reason = self.monitor.stop_reason()
            if reason is not None:
                self.reason = reason
                if self.topo.task.budget.until_success is not None and not self.monitor.success_reached():
                    return ExitCode.TARGET_MISSED
                return ExitCode.SUCCESS
            self._interrupted.wait(POLL_S)

    def _shutdown(self, fabric: Fabric) -> None:
        """Stop leaves first (they flush their last chunks), then the actor and the relays
        together (the tools' ctrl link runs through the actor's router, so relays are told
        while it is still up); escalate to signals on timeout."""
        for kinds in (("rollout", "evaluator"), ("actor", "replicator")):
            left = [n for n, s in self.launcher.children.items() if s.proc.config.kind in kinds and s.alive()]
            deadline = time.monotonic() + STOP_WAIT_S
            while left and time.monotonic() < deadline:
                # Sent again each slice: a role still starting (its command subscriber not yet
                # declared) misses a single put, and would otherwise be waited for to the end.
                for n in left:
                    fabric.publish_ctrl(fabric.keys.cmd(n), Command(target=n, verb="stop", args={}, issued_ns=time.time_ns()))
                left = self.launcher.wait_exit(left, timeout=min(STOP_RESEND_S, max(0.0, deadline - time.monotonic())))
            if left:
                self.events.append(f"no clean exit from {', '.join(left)}: terminating")
                self.launcher.stop(left, timeout=5.0)
        self.launcher.poll(stopping=True)

    def _all_local(self) -> bool:
        return all(is_local_host(p.host) for p in self.plan.processes)

    def _report(self, code: int) -> None:
        assert self.monitor is not None
        res = self.monitor.result()
        res.update(run=self.topo.run, reason=self.reason, exit_code=code,
                   restarts={n: s.restarts for n, s in self.launcher.children.items()},
                   accounting=reconcile(self.run_dir))
        (self.run_dir / "result.json").write_text(json.dumps(res, indent=1, default=str))
        try:
            plot_run(self.run_dir)
        except Exception as err:  # a missing plot must not hide the run's result
            self.events.append(f"plot failed: {err}")


def install_sigint(up: Up) -> None:
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda _signum, _frame: up.interrupt())


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
        if not pid_alive(pid):
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

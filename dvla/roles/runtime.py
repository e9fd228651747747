"""What every role process shares: the `python -m dvla.roles.<role> --config FILE` entry, logging,
CPU pinning, the fabric, signals, commands, the status queryable and the exit status.

A role module provides a class with ``__init__(config, fabric)``, ``build(swimlane)`` (declares its
lanes), ``status_extra() -> dict`` and ``policy_version`` / ``env_steps`` attributes; `main`
does the rest, so each role file reads as its lanes and nothing else.
"""

from __future__ import annotations

import argparse
import enum
import gc
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Protocol

from ..config import RoleConfig
from ..fabric import Fabric, keep_freed_buffers, load_secret, plane_config
from ..fabric.identity import IDENTITY_ENV, Identity, IdentityError, read_revoked
from ..fabric.messages import ArraySpec, ChunkSpec, Command, RoleStatus
from ..fabric.zconfig import DATA_BLOCK_WAIT_BEFORE_CLOSE_US, plane_max_message_size
from ..learn.spec import EnvSetupError, PolicySetupError
from .swimlane import Swimlane, pin_cpus, set_torch_threads

log = logging.getLogger("dvla.role")


class ExitStatus(enum.IntEnum):
    """Process exit codes of roles (the orchestrator reads them)."""

    OK = 0
    ERROR = 1
    CONFIG = 2


class Role(Protocol):
    policy_version: int
    env_steps: int

    def build(self, swimlane: Swimlane) -> None: ...

    def status_extra(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


#: threads of Zenoh's receive pool by default; one pool serves every session of a process
ZENOH_RX_THREADS = 2


def size_zenoh_rx(waiting_links: int) -> None:
    """Give Zenoh's receive pool one more thread per link whose reader may wait on purpose (an
    actor's full trajectory inbox holds a receive thread, fabric.py): otherwise the ctrl links
    sharing the pool (status, commands) wait for the learner. Call before the first session opens;
    a ``ZENOH_RUNTIME`` already set is kept."""
    if waiting_links > 0:
        os.environ.setdefault("ZENOH_RUNTIME", f"(rx: (worker_threads: {ZENOH_RX_THREADS + waiting_links}))")


def open_fabric(cfg: RoleConfig) -> Fabric:
    """The role's two sessions, as the plan wired them."""
    size_zenoh_rx(len(cfg.rollouts))  # an actor: one trajectory link per rollout
    # The largest ctrl message: a weight chunk or one snapshot reply (chunk_bytes of parameters),
    # status and commands are far smaller.
    ctrl_cap = plane_max_message_size(cfg.replication.chunk_bytes, headroom=2.0, floor=4 << 20)
    ctrl = plane_config(mode=cfg.ctrl.mode, listen=cfg.ctrl.listen, connect=cfg.ctrl.connect, shared_memory=cfg.shared_memory,
                        tls=cfg.ctrl.tls, max_message_size=ctrl_cap)
    data = None
    if cfg.data.listen or cfg.data.connect:
        data = plane_config(mode=cfg.data.mode, listen=cfg.data.listen, connect=cfg.data.connect,
                            shared_memory=cfg.shared_memory, tls=cfg.data.tls, max_message_size=data_plane_cap(cfg.task),
                            block_close_us=DATA_BLOCK_WAIT_BEFORE_CLOSE_US)
    identity = Identity.from_env()
    if identity is not None and (identity.name, identity.kind, identity.run) != (cfg.name, cfg.kind, cfg.run):
        raise IdentityError(f"{IDENTITY_ENV} names {identity.kind} {identity.name!r} of run {identity.run!r}, "
                            f"not {cfg.kind} {cfg.name!r} of run {cfg.run!r}")
    fabric = Fabric(run=cfg.run, name=cfg.name, ctrl_conf=ctrl, data_conf=data,
                    secret=load_secret(None, cfg.secret_env), identity=identity)
    # Weights come from the actor at the top of this process's chain, and from nobody else.
    fabric.weights_source = cfg.ancestors[-1] if cfg.ancestors else None
    return fabric


def data_plane_cap(task: Any) -> int:
    """The data plane's Zenoh message cap, from the sizes the task declares: the largest chunk
    its env group can send (state observations bounded at 1,024 float32 per env; images at
    two cameras of ``image_size`` squared RGB bytes plus the instruction's tokens), doubled."""
    obs = 4096
    if task.obs_mode != "state":
        obs += 2 * 3 * task.image_size ** 2 + 8 * task.instruction_tokens
    bound = ChunkSpec(obs={"obs": ArraySpec((obs,), "uint8")}, act_dim=64, T=task.chunk_steps, N=task.envs_per_rollout)
    return plane_max_message_size(bound.nbytes(), headroom=2.0)


def setup_logging(name: str) -> None:
    logging.basicConfig(
        level=os.environ.get("DVLA_LOG_LEVEL", "INFO"),
        format=f"%(asctime)s %(levelname)s {name} %(name)s: %(message)s",
        stream=sys.stderr,
    )


class RoleHost:
    """Runs one role: lanes, commands, status, signals; returns the exit status."""

    def __init__(self, cfg: RoleConfig, fabric: Fabric, role: Role) -> None:
        self.cfg = cfg
        self.fabric = fabric
        self.role = role
        self.swimlane = Swimlane(cfg.name)
        self.state = "starting"
        self.started = time.time()
        self._rate_mark = (time.monotonic(), 0)
        self._rate = 0.0
        self._rate_lock = threading.Lock()
        #: where the process runs: CPU affinity and torch threads, as set by main()
        self.placement: dict[str, Any] = {}

    def _on_command(self, sender: str, cmd: Command) -> None:
        if cmd.verb == "stop" and self.swimlane.stop_event.is_set():
            return  # the orchestrator repeats a stop until the process is gone
        log.info("command %s from %s", cmd.verb, sender)
        if cmd.verb == "stop":
            self.state = "stopping"
            self.swimlane.stop()
        elif cmd.verb == "revoke":
            self.fabric.revoked.add(str(cmd.args["name"]))
        else:
            handler = getattr(self.role, "on_command", None)
            if handler is not None:
                handler(cmd)

    def steps_per_s(self) -> float:
        with self._rate_lock:
            t0, s0 = self._rate_mark
            now, steps = time.monotonic(), self.role.env_steps
            if now - t0 >= 1.0:
                self._rate = (steps - s0) / (now - t0)
                self._rate_mark = (now, steps)
            return self._rate

    def status(self, _req: Any = None) -> RoleStatus:
        return RoleStatus(
            name=self.cfg.name,
            kind=self.cfg.kind,
            node=self.cfg.node,
            rack=self.cfg.rack,
            pid=os.getpid(),
            state=self.state,
            policy_version=int(self.role.policy_version),
            env_steps=int(self.role.env_steps),
            steps_per_s=float(self.steps_per_s()),
            lanes=_lane_floats(self.swimlane.stats()),
            planes=self.fabric.accounting.snapshot(),  # ints only
            extra={**self.role.status_extra(), "placement": {**self.placement, "lanes": self.swimlane.affinity()}},
            time_ns=time.time_ns(),
        )

    def run(self) -> ExitStatus:
        keys = self.fabric.keys
        self.fabric.revoked |= read_revoked(self.cfg.run_dir)  # revoked before this start (`dvla identity revoke`)
        # Wiring of the shared parts; each role wires its own data flow in build().
        self.fabric.on_ctrl(keys.cmd(self.cfg.name), Command, self._on_command)  # commands for this role
        self.fabric.on_ctrl(keys.cmd("all"), Command, self._on_command)  # commands for every role
        self.fabric.serve(keys.status(self.cfg.name), self.status)  # `dvla status` and the orchestrator
        self.role.build(self.swimlane)
        if self.cfg.lane_cpus:
            try:
                self.swimlane.pin(self.cfg.lane_cpus)
            except ValueError as err:
                log.error("%s: bad lane_cpus in the config: %s", self.cfg.name, err)
                return ExitStatus.CONFIG
        self.fabric.declare_alive()  # membership: gone when this process is
        # What is built so far (modules, policy, envs) lives as long as the process: out of the
        # cyclic collector's full passes, which would walk it again on every one (ManiSkill's
        # env.close() runs one per env, ~0.3-1 s each in a role on a busy 2-core machine).
        gc.freeze()
        self.swimlane.start()
        self.state = "running"
        log.info("%s running (pid %d)", self.cfg.name, os.getpid())
        self.swimlane.wait()
        self.state = "stopping"
        unjoined = self.swimlane.join(timeout=10.0)
        if unjoined:
            log.error("lanes did not exit: %s", ", ".join(unjoined))
        error = self.swimlane.error
        self._write_summary(error)
        if error is not None:
            self.state = "error"
            log.error("%s stopped with an error in lane %s", self.cfg.name, error)
            return ExitStatus.ERROR
        log.info("%s stopped cleanly", self.cfg.name)
        return ExitStatus.OK

    def _write_summary(self, error: Any) -> None:
        path = Path(self.cfg.run_dir) / "summaries" / f"{self.cfg.name}.json"
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            st = self.status()
            doc = {k: getattr(st, k) for k in ("name", "kind", "policy_version", "env_steps", "lanes", "planes", "extra")}
            doc.update(error=None if error is None else str(error), wall_s=time.time() - self.started)
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(doc, indent=1, sort_keys=True, default=str))
            tmp.replace(path)
        except OSError as err:
            log.warning("cannot write summary %s: %s", path, err)


def _lane_floats(stats: dict[str, dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Lane stats as the float map RoleStatus carries (booleans become 0/1)."""
    return {
        lane: {k: float(v) for k, v in st.items() if isinstance(v, (int, float))}
        for lane, st in stats.items()
    }


def main(role_factory: Any, argv: list[str] | None = None) -> int:
    """Entry point shared by `python -m dvla.roles.<role>`."""
    parser = argparse.ArgumentParser(description="run one dvla role process")
    parser.add_argument("--config", required=True, help="RoleConfig JSON written by the orchestrator")
    args = parser.parse_args(argv)
    try:
        cfg = RoleConfig.from_json(Path(args.config).read_text())
    except (OSError, ValueError, KeyError, TypeError) as err:
        print(f"dvla role: cannot read config {args.config}: {err}", file=sys.stderr)
        return ExitStatus.CONFIG
    setup_logging(cfg.name)
    # PyTorch's compiled-kernel cache (fused CPU Adam creates it) goes in the run, not /tmp.
    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(Path(cfg.run_dir) / "cache" / "torchinductor"))
    if cfg.cpus:
        pin_cpus(cfg.cpus)
    # One intra-op thread per role: the lanes are the concurrency; more threads only contend.
    threads = set_torch_threads(1)
    # Chunks pass through MiB-sized buffers: keep freed ones in the heap (dvla/fabric/heap.py).
    kept = keep_freed_buffers()
    fabric = open_fabric(cfg)
    role = None
    host: RoleHost | None = None
    try:
        role = role_factory(cfg, fabric)
        host = RoleHost(cfg, fabric, role)
        host.placement = {
            "cpus": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "torch_threads": threads,
            "keep_freed_buffers": kept,
        }

        def _on_signal(signum: int, _frame: Any) -> None:
            log.info("signal %d: stopping", signum)
            host.swimlane.stop()

        signal.signal(signal.SIGTERM, _on_signal)
        signal.signal(signal.SIGINT, _on_signal)
        code = host.run()
        role.failed = code != ExitStatus.OK  # what its close() may record (e.g. counter files)
        return int(code)
    except (EnvSetupError, PolicySetupError) as err:  # a setting to fix, not a bug: its one line, no traceback
        log.error("%s cannot start: %s", cfg.name, err)
        return ExitStatus.CONFIG
    except Exception:
        log.exception("%s failed", cfg.name)
        return ExitStatus.ERROR
    finally:
        if role is not None:
            try:
                role.close()
            except Exception:
                log.exception("closing %s", cfg.name)
        fabric.close()

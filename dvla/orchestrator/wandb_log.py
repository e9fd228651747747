"""Weights & Biases copy of a run's TensorBoard scalars (``logging.wandb`` in the topology).

W&B is optional and may be remote, so it must never delay or fail a run: everything W&B does
happens on one named thread (``wandb``), fed through a bounded queue that drops (and counts) a
round rather than wait; a failed ``wandb.init`` is one warning line and the run goes on without
W&B; :meth:`WandbLog.close` waits a bounded time. docs/architecture.md ("Scalars: TensorBoard and
W&B") says what each mode writes and why W&B's telemetry is off.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import queue
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil

from ..config import Topology, WandbConfig
from .topology import topology_to_dict

#: rounds of scalars waiting for the W&B thread (one status round a second, plus evaluations):
#: minutes of backlog while ``wandb.init`` is still reaching the server
QUEUE_ROUNDS = 1024
#: how often the W&B thread looks at the stop event while the queue is empty, seconds
POLL_S = 0.2
#: what :meth:`WandbLog.close` waits beyond ``finish_timeout_s`` (the last rounds, the service's exit)
CLOSE_MARGIN_S = 5.0
#: the W&B service process the wandb library starts (a child of this process)
SERVICE_NAME = "wandb-core"
#: longest error text quoted in the warning line
MAX_ERROR_CHARS = 240


def missing_wandb(topo: Topology) -> str | None:
    """The one-line error of a topology that sets ``logging.wandb`` where wandb is not
    installed, or None (checked by `dvla up` before anything starts)."""
    if topo.logging.wandb is None or importlib.util.find_spec("wandb") is not None:
        return None
    return f"{topo.source}: logging.wandb: wandb is not installed (pip install 'dvla[wandb]', or remove logging.wandb)"


def open_hint(cfg: WandbConfig, run_dir: Path) -> str:
    """How to open the W&B run, for `dvla up`'s opening lines (the exact directory or URL is
    known once ``wandb.init`` is done: it follows as an event line)."""
    if cfg.mode == "offline":
        return f"wandb sync {run_dir / 'wandb'}/offline-run-*   (offline: W&B project {cfg.project})"
    return f"online, W&B project {cfg.project} (the run's URL follows once W&B is reached)"


@dataclass(frozen=True)
class ScalarRound:
    """One round of scalars for W&B: a status collection or an evaluation."""

    #: the learner's env steps: the x axis of every W&B chart
    env_steps: int
    #: scalar values by TensorBoard tag (``train/approx_kl``, ``eval/success_once``, ...)
    scalars: dict[str, float]


class WandbLog:
    """A W&B run fed from the monitor, its thread started at once; :meth:`log` never blocks."""

    def __init__(self, cfg: WandbConfig, run_dir: Path, run: str, config: dict[str, Any]) -> None:
        self.cfg = cfg
        self.run_dir = run_dir
        self._run = run
        self._config = config
        self._queue: queue.Queue[ScalarRound] = queue.Queue(maxsize=QUEUE_ROUNDS)
        self._stop = threading.Event()
        #: set once W&B is off (init or a log failed): rounds are no longer queued
        self._off = threading.Event()
        self._notes: list[str] = []
        self._notes_lock = threading.Lock()
        #: rounds dropped because the queue was full
        self.dropped = 0
        # a daemon: a W&B call that never returns must not hold the orchestrator's exit (close()
        # stops waiting for it after its bound)
        self._thread = threading.Thread(target=self._main, name="wandb", daemon=True)
        self._thread.start()

    @classmethod
    def start(cls, topo: Topology, run_dir: Path, processes: int) -> WandbLog | None:
        """The run's W&B log, its thread started (None when ``logging.wandb`` is not set)."""
        if topo.logging.wandb is None:
            return None
        task = topology_to_dict(topo)["task"]
        config = {"run": topo.run, "mode": topo.mode, "seed": topo.seed, "processes": processes, "task": task}
        return cls(topo.logging.wandb, run_dir, topo.run, config)

    def log(self, env_steps: int, scalars: dict[str, float]) -> None:
        """Queue one round of scalars at `env_steps`; drops it (counted) when the queue is full."""
        if self._off.is_set():
            return
        try:
            self._queue.put_nowait(ScalarRound(env_steps, dict(scalars)))
        except queue.Full:
            self.dropped += 1

    def take_notes(self) -> list[str]:
        """Lines for the user since the last call: where the W&B run is, or why there is none."""
        with self._notes_lock:
            notes, self._notes = self._notes, []
        return notes

    def close(self) -> list[str]:
        """Finish the W&B run, waiting at most ``finish_timeout_s`` + CLOSE_MARGIN_S; stop any W&B
        service process left; return the last notes."""
        self._stop.set()
        wait_s = self.cfg.finish_timeout_s + CLOSE_MARGIN_S
        self._thread.join(wait_s)
        if self._thread.is_alive():
            self._note(f"warning: logging.wandb: W&B did not finish within {wait_s:.0f} s; stopped it"
                       " (the run's scalars are all in its TensorBoard files)")
        left = stop_service_processes()
        if left:
            self._note(f"logging.wandb: stopped {left} W&B service process(es) left running")
        if self.dropped:
            self._note(f"logging.wandb: {self.dropped} round(s) of scalars not sent to W&B (queue full)")
        return self.take_notes()

    # --- the W&B thread ------------------------------------------------------------------------

    def _note(self, line: str) -> None:
        with self._notes_lock:
            self._notes.append(line)

    def _main(self) -> None:
        wandb: Any = None
        try:
            # W&B's usage telemetry has its own exporter that holds the process's exit for up to
            # 30 s without a network; it is W&B's, not the user's data
            os.environ["WANDB_ERROR_REPORTING"] = "false"
            # the terminal is the live view's; what W&B prints before `silent` applies (its
            # login line) would land in it
            os.environ.setdefault("WANDB_SILENT", "true")
            wandb = importlib.import_module("wandb")
            run = self._init(wandb)
        except BaseException as err:  # whatever W&B raises, the run goes on without it
            self._off.set()
            self._note(f"warning: logging.wandb: W&B {self.cfg.mode} run did not start ({_first_line(err)});"
                       f" the run goes on without W&B (its scalars are in {self.run_dir / 'tb'})")
            _teardown(wandb)
            return
        try:
            self._note(self._where(run))
            self._drain(run)
        except BaseException as err:  # as above: W&B's failure is never the run's
            self._off.set()
            self._note(f"warning: logging.wandb: W&B stopped logging ({_first_line(err)}); the run goes on without W&B")
        try:
            run.finish()
        except BaseException as err:  # as above: W&B's failure is never the run's
            self._note(f"warning: logging.wandb: W&B finish failed ({_first_line(err)})")
        _teardown(wandb)

    def _init(self, wandb: Any) -> Any:
        cfg = self.cfg
        settings: dict[str, Any] = {
            "init_timeout": cfg.init_timeout_s,
            "console": "off",  # the live view owns the terminal; roles' logs are files already
            "silent": True,
            "disable_git": True,
            "save_code": False,
        }
        if "finish_timeout" in getattr(wandb.Settings, "model_fields", {}):  # newer wandb versions
            settings["finish_timeout"] = cfg.finish_timeout_s
        run = wandb.init(
            project=cfg.project, entity=cfg.entity, name=cfg.name or self._run, group=self._run,
            tags=list(cfg.tags) or None, config=self._config, dir=str(self.run_dir), mode=cfg.mode,
            settings=wandb.Settings(**settings),
        )
        # every chart's x axis is the learner's env steps, as in TensorBoard
        run.define_metric("env_steps")
        run.define_metric("*", step_metric="env_steps")
        return run

    def _where(self, run: Any) -> str:
        if self.cfg.mode == "offline":
            sync_dir = getattr(run.settings, "sync_dir", None) or str(Path(run.dir).parent)
            return f"wandb: offline run in {sync_dir}; upload it with: wandb sync {sync_dir}"
        return f"wandb: {getattr(run, 'url', None) or run.get_url()}"

    def _drain(self, run: Any) -> None:
        """Log queued rounds until stopped and the queue is empty."""
        while True:
            try:
                item = self._queue.get(timeout=POLL_S)
            except queue.Empty:
                if self._stop.is_set():
                    return
                continue
            run.log({"env_steps": item.env_steps, **item.scalars})


def _teardown(wandb: Any) -> None:
    """Stop the W&B service of this process (nothing to do when wandb was never imported)."""
    if wandb is None or not hasattr(wandb, "teardown"):
        return
    try:
        wandb.teardown()
    except BaseException:  # close() still stops a service left running
        pass


def stop_service_processes(wait_s: float = 3.0) -> int:
    """Terminate (then kill) the W&B service processes among this process's descendants; how many
    were found."""
    try:
        found = [p for p in psutil.Process().children(recursive=True) if _is_service(p)]
    except psutil.Error:
        return 0
    for p in found:
        try:
            p.terminate()
        except psutil.Error:
            pass
    _gone, alive = psutil.wait_procs(found, timeout=wait_s)
    for p in alive:
        try:
            p.kill()
        except psutil.Error:
            pass
    psutil.wait_procs(alive, timeout=wait_s)
    return len(found)


def _is_service(p: psutil.Process) -> bool:
    try:
        return p.name() == SERVICE_NAME or any(Path(a).name == SERVICE_NAME for a in p.cmdline()[:1])
    except psutil.Error:
        return False


def _first_line(err: BaseException) -> str:
    text = (str(err).strip().splitlines() or [""])[0]
    if len(text) > MAX_ERROR_CHARS:
        text = text[:MAX_ERROR_CHARS - 3] + "..."
    return f"{type(err).__name__}: {text}" if text else type(err).__name__

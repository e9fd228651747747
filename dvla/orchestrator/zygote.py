"""Warm role starts: one process per run imports what the run's local roles import (torch, the
simulator, the policy family, the role modules) once, and forks each local role from there.

Why: a role process spends most of a short run's CPU importing (torch ~2 s, ManiSkill ~3 s,
transformers ~3 s of CPU each, in every role, again at every restart). Forked from a process
that has them imported, a role starts in milliseconds and shares those pages with its siblings.

How it stays a plain role process:
- the zygote forks only while it has a single thread (checked after its imports; otherwise it
  says why and the launcher starts every role with ``python -m`` as before);
- the child does what ``subprocess.Popen(start_new_session=True, preexec_fn=die_with_parent)``
  and ``python -m dvla.roles.<kind> --config <file>`` would: a session of its own, death with
  its parent (the zygote, which dies with ``dvla up``), stdin from /dev/null, stdout and stderr
  to the role's log, the role's environment and command line (``ps`` and ``pgrep -f`` see the
  role's ``python -m dvla.roles.<kind> --config ...``), then the module run as ``__main__`` and
  the interpreter's normal exit;
- ``dvla up`` supervises it through :class:`ForkedRole`, which answers as a ``Popen`` does
  (``pid``, ``poll``, ``wait``, ``returncode``): the zygote reports each child's exit status.

Only roles started on this host with the run's own environment (the role's credential aside)
are forked: as they are, or into their node's network namespace (``setns`` in the child, where
the plain start runs ``ip netns exec``); over SSH or as Slurm steps they start as before.
``DVLA_WARM_START=0`` turns it off. The protocol is one JSON object per line: requests on the zygote's stdin,
``{"ready": ...}``, ``{"pid": ..., "id": ...}`` and ``{"exit": pid, "code": ...}`` on its stdout.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

from .process import die_with_parent

log = logging.getLogger("dvla.zygote")

#: the environment variable that turns warm starts off ("0")
WARM_START_ENV = "DVLA_WARM_START"
#: seconds the launcher waits for the zygote's imports before starting roles the plain way
READY_TIMEOUT_S = 120.0


def warm_start_enabled(env: dict[str, str]) -> bool:
    return env.get(WARM_START_ENV, "1") != "0"


def preload_modules(kinds: set[str], task: Any) -> list[str]:
    """What the local roles of a run import: their role modules, ManiSkill for a ManiSkill task,
    the policy family's module."""
    from ..learn.envs import is_maniskill
    from ..learn.policies import policy_module

    mods = [f"dvla.roles.{k}" for k in sorted(kinds) if k != "router"]
    if kinds - {"router", "replicator"}:  # the roles that build envs or read their spec
        if is_maniskill(task):
            mods.append("mani_skill.envs")
        family = policy_module(task.policy)
        if family is not None:
            mods.append(family)
    return mods


# --- the zygote process ---------------------------------------------------------------------


def _threads() -> int:
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return threading.active_count()


#: where replies go: the launcher's pipe, kept apart from fd 1 (which is pointed at the log, so
#: that nothing an imported module prints can break a reply line)
_REPLY_FD = 1


def _reply(doc: dict[str, Any]) -> None:
    os.write(_REPLY_FD, (json.dumps(doc) + "\n").encode())


def serve(preload: list[str]) -> dict[str, Any] | None:
    """The zygote's loop: import `preload`, then fork a child per request. Returns the request in
    a forked child (which then runs the role); returns None in the zygote when the launcher
    hangs up (its stdin closes)."""
    global _REPLY_FD
    _REPLY_FD = os.dup(1)
    os.dup2(2, 1)
    for name in preload:
        try:
            importlib.import_module(name)
        except Exception as err:  # the role will say it better when it imports the module itself
            print(f"dvla zygote: cannot import {name}: {err}", file=sys.stderr)
    threads = _threads()
    if threads != 1:  # forking a process with threads may copy a lock some thread held
        _reply({"ready": False, "why": f"{threads} threads after importing {', '.join(preload)}"})
        return None
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_initialized():  # a CUDA context does not survive a fork
        _reply({"ready": False, "why": f"CUDA initialised by importing {', '.join(preload)}"})
        return None
    zygote = os.getpid()
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    _reply({"ready": True, "pid": zygote})
    pending = b""
    children: set[int] = set()
    while True:
        ready, _, _ = select.select([0, wake_r], [], [], 1.0)
        if wake_r in ready:
            os.read(wake_r, 4096)
        while children:  # reap: each exit status goes to the launcher
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            children.discard(pid)
            _reply({"exit": pid, "code": os.waitstatus_to_exitcode(status)})
        if 0 not in ready:
            continue
        data = os.read(0, 65536)
        if not data:  # the launcher is gone or done: children die with this process
            return None
        pending += data
        while b"\n" in pending:
            line, pending = pending.split(b"\n", 1)
            req = json.loads(line)
            sys.stdout.flush()
            sys.stderr.flush()
            led_r, led_w = os.pipe()
            pid = os.fork()
            if pid == 0:
                os.close(led_r)
                signal.set_wakeup_fd(-1)
                signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                os.close(wake_r)
                os.close(wake_w)
                os.close(_REPLY_FD)
                _lead_own_session(zygote, req.get("netns", ""))
                os.write(led_w, b".")  # the launcher may signal its process group from now on
                os.close(led_w)
                return req
            os.close(led_w)
            os.read(led_r, 1)  # (empty if the child died first: its exit is reported as usual)
            os.close(led_r)
            children.add(pid)
            _reply({"pid": pid, "id": req["id"]})


def _lead_own_session(zygote: int, netns: str) -> None:
    """In the forked child, before the zygote names it: its network namespace (as `ip netns
    exec` would), a session of its own (the launcher signals its process group) and death with
    the zygote."""
    if netns:
        from .netns import enter_netns

        try:
            enter_netns(netns)
        except OSError as err:
            print(f"dvla zygote: cannot enter network namespace {netns}: {err}", file=sys.stderr)
            os._exit(1)
    os.setsid()
    die_with_parent()
    if os.getppid() != zygote:  # the zygote died before the line above
        os._exit(1)


def _become(req: dict[str, Any]) -> None:
    """In the forked child: the process `python -m <module> <args>` would have been."""
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    out = os.open(req["log"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    os.dup2(out, 1)
    os.dup2(out, 2)
    os.close(null)
    os.close(out)
    argv = [sys.executable, "-m", req["module"], *req["args"]]
    try:  # (before the environment changes: it finds the command line's memory beside it)
        from setproctitle import setproctitle

        setproctitle(" ".join(argv))
    except ImportError:
        pass
    os.environ.clear()
    os.environ.update(req["env"])
    os.chdir(req["cwd"])
    sys.argv = [req["module"], *req["args"]]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="dvla's warm-start process (started by dvla up)")
    ap.add_argument("--preload", action="append", default=[], help="module to import before forking")
    ap.add_argument("--run-dir", default="", help="the run it serves (for ps and pgrep)")
    args = ap.parse_args(argv)
    req = serve(args.preload)
    if req is None:
        return 0
    import runpy

    _become(req)
    sys.modules.pop(req["module"], None)  # imported here only for its imports: run afresh, as -m does
    runpy.run_module(req["module"], run_name="__main__", alter_sys=True)
    return 0


# --- the launcher's side ----------------------------------------------------------------------


class ForkedRole:
    """A role forked by the zygote, supervised as a ``subprocess.Popen`` is."""

    stdin = None

    def __init__(self, pid: int, exited: Callable[[int], int | None], done: threading.Event) -> None:
        self.pid = pid
        self._exited = exited
        self._done = done
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self._exited(self.pid)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout or 0.0)
            self._done.wait(0.05 if left is None else min(0.05, left))
        assert self.returncode is not None
        return self.returncode


class Zygote:
    """The launcher's handle on its zygote process; after `wait_ready`, `why_not` says why it
    cannot fork when it cannot."""

    def __init__(self, preload: list[str], env: dict[str, str], run_dir: Path, log_path: Path) -> None:
        self._lock = threading.Lock()
        self._exits: dict[int, int] = {}
        self._started: dict[int, int] = {}  # request id -> pid
        self._changed = threading.Event()
        self._next_id = 0
        self.why_not = ""
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(log_path, "ab", buffering=0) as logf:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "dvla.orchestrator.zygote", "--run-dir", str(run_dir),
                 *[a for m in preload for a in ("--preload", m)]],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=logf, env=env,
                start_new_session=True, preexec_fn=die_with_parent,
            )
        self.ready = False
        self._reader = threading.Thread(target=self._read, name="zygote-reader", daemon=True)
        self._ready_event = threading.Event()
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            try:
                doc = json.loads(raw)
            except ValueError:
                continue
            with self._lock:
                if "ready" in doc:
                    self.ready = bool(doc["ready"])
                    self.why_not = doc.get("why", "")
                    self._ready_event.set()
                elif "exit" in doc:
                    self._exits[int(doc["exit"])] = int(doc["code"])
                elif "pid" in doc:
                    self._started[int(doc["id"])] = int(doc["pid"])
            self._changed.set()
        # the zygote is gone: its children died with it (PR_SET_PDEATHSIG)
        with self._lock:
            if not self._ready_event.is_set():
                self.why_not = self.why_not or f"the warm-start process exited ({self.proc.poll()})"
            self.ready = False
        self._ready_event.set()
        self._changed.set()

    def wait_ready(self, timeout: float = READY_TIMEOUT_S) -> bool:
        if not self._ready_event.wait(timeout):
            self.why_not = f"not ready after {timeout:.0f} s"
            self.close()
        return self.ready

    def _exit_of(self, pid: int) -> int | None:
        with self._lock:
            if pid in self._exits:
                return self._exits[pid]
            gone = not self.ready and self.proc.poll() is not None
        if gone:  # the zygote died and could not report: the child died with it
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return -signal.SIGKILL
        return None

    def spawn(self, module: str, args: list[str], env: dict[str, str], log_path: Path, netns: str = "",
              timeout: float = 30.0) -> ForkedRole | None:
        """Fork `python -m module args` with `env`, output appended to `log_path`, inside network
        namespace `netns` ("" for this one); None when the zygote cannot (the caller starts the
        process itself)."""
        with self._lock:
            if not self.ready or self.proc.stdin is None:
                return None
            self._next_id += 1
            rid = self._next_id
        req = {"id": rid, "module": module, "args": args, "env": env, "cwd": os.getcwd(), "log": str(log_path),
               "netns": netns}
        try:
            self.proc.stdin.write((json.dumps(req) + "\n").encode())
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError):
            return None
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                pid = self._started.pop(rid, None)
                alive = self.ready
            if pid is not None:
                return ForkedRole(pid, self._exit_of, self._changed)
            if not alive or time.monotonic() > deadline:
                return None
            self._changed.wait(0.05)
            self._changed.clear()

    def close(self) -> None:
        """Hang up (the zygote exits; a child still running dies with it) and reap it."""
        if self.proc.stdin is not None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


if __name__ == "__main__":
    raise SystemExit(main())

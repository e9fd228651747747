"""Starts and supervises role processes: one OS process per role, restarted with backoff.

Children run in their own session (so a terminal's Ctrl-C reaches only the orchestrator, which
then stops them in order) and die with the orchestrator (PR_SET_PDEATHSIG), so no orphan
survives even a `kill -9` of `dvla up`.
"""

from __future__ import annotations

import errno
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from ..fabric.identity import IDENTITY_ENV, Identity
from .process import CommandWrapper, Process, Supervised, die_with_parent, endpoint_address, is_local_host
from .zygote import Zygote, warm_start_enabled

log = logging.getLogger("dvla.launcher")




#: a role's exit code for a setting it cannot run with (``roles.runtime.ExitStatus.CONFIG``: an
#: env or a policy checkpoint that cannot be set up): restarting would fail the same way
CONFIG_EXIT = 2

class Launcher:
    """Owns every child process of a run."""

    #: seconds before the first restart of a role that died young; doubled on each restart
    BACKOFF_S = 1.0

    def __init__(self, run_dir: Path, env: dict[str, str], *, max_restarts: int = 3,
                 operator: Identity | None = None) -> None:
        self.run_dir = run_dir
        self.env = env
        #: issues each child's identity (kept across its restarts); None: children run without one
        self.operator = operator
        #: role name -> its credential text (environment of a local child, stdin of a remote one)
        self.identities: dict[str, str] = {}
        self.max_restarts = max_restarts
        #: how a role's argv becomes the command that starts it (in a namespace, over ssh)
        self.wrap = CommandWrapper()
        self.children: dict[str, Supervised] = {}
        #: the modules a warm-start process imports for the given role kinds (None: no warm starts);
        #: set by the orchestrator, which knows the task (dvla/orchestrator/zygote.py)
        self.preload: Callable[[set[str]], list[str]] | None = None
        self.zygote: Zygote | None = None

    def add(self, proc: Process) -> Supervised:
        cfg = proc.config
        config_path = self.run_dir / "roles" / f"{cfg.name}.json"
        config_path.parent.mkdir(parents=True, exist_ok=True)
        config_path.write_text(cfg.to_json())
        log_path = self.run_dir / "logs" / f"{cfg.name}.log"
        log_path.parent.mkdir(parents=True, exist_ok=True)
        if self.operator is not None:
            self.identities[cfg.name] = self.operator.issue(cfg.kind, cfg.name).to_text()
        sup = Supervised(proc=proc, config_path=config_path, log_path=log_path)
        self.children[cfg.name] = sup
        return sup

    def command(self, sup: Supervised) -> list[str]:
        """The command line that starts `sup`, wrapped to run in its namespace or on its host."""
        return self.wrap(sup.proc, _role_argv(sup))

    def _fork_into(self, sup: Supervised) -> str | None:
        """The network namespace ("" for none) a warm start forks `sup` into, or None when it
        cannot be forked here (over SSH, as a Slurm step, with a payload on its stdin)."""
        argv = _role_argv(sup)
        if self.wrap.stdin_payload(sup.proc, argv, None) is not None or self.wrap.output_path(sup) is not None:
            return None
        return self.wrap.fork_into(sup.proc)

    def _warm_up(self) -> None:
        """Start the warm-start process for the roles that start here as they are, and wait for
        its imports; on any trouble, say why once and start every role the plain way."""
        kinds = {s.proc.config.kind for s in self.children.values() if self._fork_into(s) is not None}
        if not kinds or self.preload is None or self.zygote is not None or not warm_start_enabled(self.env):
            return
        zygote = Zygote(self.preload(kinds), self.env, self.run_dir, self.run_dir / "logs" / "zygote.log")
        if zygote.wait_ready():
            self.zygote = zygote
        else:
            log.warning("warm starts off (roles start with python -m): %s", zygote.why_not)
            zygote.close()

    def close(self) -> None:
        """After the last child: end the warm-start process."""
        if self.zygote is not None:
            self.zygote.close()
            self.zygote = None

    def start(self, sup: Supervised) -> None:
        argv = self.command(sup)
        role_argv = _role_argv(sup)
        identity = self.identities.get(sup.name)
        payload = self.wrap.stdin_payload(sup.proc, role_argv, identity)
        out_path = self.wrap.output_path(sup)
        env = self.wrap.child_env(sup.proc, self.env if identity is None else {**self.env, IDENTITY_ENV: identity})
        if self.zygote is not None and (netns := self._fork_into(sup)) is not None and \
                {k: v for k, v in env.items() if k != IDENTITY_ENV} == self.env:
            with open(sup.log_path, "ab", buffering=0) as logf:
                where = f" in network namespace {netns}" if netns else ""
                logf.write(f"--- start {time.strftime('%H:%M:%S')} (restart {sup.restarts}, forked warm{where}): "
                           f"{' '.join(role_argv)}\n".encode())
            forked = self.zygote.spawn(role_argv[2], role_argv[3:], env, sup.log_path, netns=netns)
            if forked is not None:
                sup.popen = forked  # type: ignore[assignment]  (answers as a Popen does)
                sup.started_at = time.monotonic()
                log.info("started %s (pid %d, forked warm)", sup.name, forked.pid)
                return
        logf = open(sup.log_path, "ab", buffering=0)
        outf = None
        try:
            logf.write(f"--- start {time.strftime('%H:%M:%S')} (restart {sup.restarts}): {' '.join(argv)}\n".encode())
            if out_path is not None:
                out_path.parent.mkdir(parents=True, exist_ok=True)
                outf = open(out_path, "wb")
            sup.popen = subprocess.Popen(
                argv,
                # A payload (config, secret) goes on stdin, which then stays open: closing it asks
                # the process to stop, and it closes by itself when this process dies.
                stdin=subprocess.PIPE if payload is not None else subprocess.DEVNULL,
                stdout=outf if outf is not None else logf,
                stderr=logf if outf is not None else subprocess.STDOUT,
                env=env,
                start_new_session=True,
                preexec_fn=die_with_parent,
            )
        finally:
            logf.close()
            if outf is not None:
                outf.close()
        if payload is not None:
            assert sup.popen.stdin is not None
            try:
                sup.popen.stdin.write(payload)
                sup.popen.stdin.flush()
            except (BrokenPipeError, OSError):
                pass  # exited at once; poll() reports it
        sup.started_at = time.monotonic()
        log.info("started %s (pid %d)", sup.name, sup.popen.pid)

    def _exited(self, sup: Supervised, code: int) -> list[str]:
        """Bookkeeping after a child exited: release its stdin, let the wrapper collect its output."""
        _close_stdin(sup)
        note = self.wrap.finished(sup, code)
        return [note] if note else []

    def start_all(self, ready_timeout_s: float = 30.0) -> None:
        """Start every child in plan order (actors, replicators, leaves), each once its parent's
        control-plane listener accepts connections.

        A Zenoh client connects to the first of its endpoints that answers: a leaf started before
        its replicator listens would attach to a further ancestor (its fallback) and stay there,
        so that ancestor would carry the leaf's copy of every version and the tree would be a star.
        """
        self._warm_up()
        by_name = {sup.name: sup for sup in self.children.values()}
        ready: set[str] = set()
        for sup in self.children.values():
            parent = by_name.get(sup.proc.config.parent or "")
            if parent is not None and parent.name not in ready:
                if not _wait_listening(parent, ready_timeout_s):
                    log.warning("%s: parent %s not listening after %.0f s; starting anyway",
                                sup.name, parent.name, ready_timeout_s)
                ready.add(parent.name)
            self.start(sup)

    def poll(self, stopping: bool) -> list[str]:
        """Reap exited children; restart crashed ones with backoff. Returns events (log lines)."""
        events = []
        now = time.monotonic()
        for sup in self.children.values():
            if sup.failed or sup.finished:
                continue
            if sup.popen is None:
                if not stopping and now >= sup.next_start:
                    self.start(sup)
                    events.append(f"restarted {sup.name} (restart {sup.restarts})")
                continue
            code = sup.popen.poll()
            if code is None:
                continue
            sup.exit_codes.append(code)
            events.extend(self._exited(sup, code))
            sup.popen = None
            if stopping or code == 0:
                sup.finished = True
                events.append(f"{sup.name} exited ({code})")
                continue
            if code == CONFIG_EXIT:  # a setting to fix (its log's last line says which): same every time
                sup.failed = True
                events.append(f"{sup.name} cannot start with this configuration (exit {code}; see its log): not restarted")
                continue
            if sup.restarts >= self.max_restarts:
                sup.failed = True
                events.append(f"{sup.name} failed {sup.restarts + 1} times (last exit {code}); giving up")
                continue
            # A role that ran a while before crashing gets its backoff reset.
            ran = now - sup.started_at
            delay = self.BACKOFF_S * (2 ** sup.restarts if ran < 30 else 1)
            sup.restarts += 1
            sup.next_start = now + delay
            events.append(f"{sup.name} crashed (exit {code}); restarting in {delay:.1f} s")
            if sup.proc.config.group is not None:
                events.extend(self._restart_group(sup))
        return events

    def _restart_group(self, crashed: Supervised) -> list[str]:
        """A learner group cannot lose a rank: when one dies, the others are killed too (their
        collectives would fail or hang) and the whole group restarts together, from rank 0's last
        checkpoint, counted as one restart of each member."""
        members = [s for s in self.children.values() if s.proc.config.group is not None]
        killed = []
        for sup in members:
            if sup is crashed or sup.failed or sup.finished:
                continue
            if sup.alive():
                if not self._kill(sup, wait_s=10):  # never reaped: let go of it as killed
                    self._exited(sup, -9)
                    sup.popen = None
                killed.append(sup.name)
            sup.restarts = max(sup.restarts, crashed.restarts)
            sup.next_start = max(sup.next_start, crashed.next_start)
        crashed.next_start = max(s.next_start for s in members)
        for sup in members:
            sup.next_start = crashed.next_start
        return [f"learner group restarts from its last checkpoint ({crashed.name} died"
                + (f"; killed {', '.join(killed)})" if killed else ")")]

    def stop(self, names: list[str], timeout: float) -> None:
        """SIGTERM the named children, then SIGKILL whoever is still up after `timeout`."""
        sups = [self.children[n] for n in names if self.children[n].alive()]
        for sup in sups:
            if sup.popen is not None and sup.popen.stdin is not None:
                _close_stdin(sup)  # a hang-up: the remote side stops the role and sends its files
            else:
                _signal(sup, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for sup in sups:
            remaining = max(0.0, deadline - time.monotonic())
            try:
                sup.popen.wait(timeout=remaining)  # type: ignore[union-attr]
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s: killing", sup.name, timeout)
                _signal(sup, signal.SIGKILL)
                sup.popen.wait(timeout=5)  # type: ignore[union-attr]

    def wait_exit(self, names: list[str], timeout: float) -> list[str]:
        """Wait for the named children to exit by themselves; returns those still running."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not any(self.children[n].alive() for n in names):
                return []
            time.sleep(0.05)
        return [n for n in names if self.children[n].alive()]

    def kill_all(self) -> None:
        for sup in self.children.values():
            if sup.alive() and self._kill(sup, wait_s=5):
                sup.finished = True

    def _kill(self, sup: Supervised, wait_s: float) -> bool:
        """Hang up on `sup`, SIGKILL its process group and reap it; False if it is still there after `wait_s`."""
        _close_stdin(sup)
        _signal(sup, signal.SIGKILL)
        try:
            code = sup.popen.wait(timeout=wait_s)  # type: ignore[union-attr]
        except subprocess.TimeoutExpired:
            return False
        sup.exit_codes.append(code)
        self._exited(sup, code)
        sup.popen = None
        return True

    def pids(self) -> dict[str, int]:
        return {n: s.popen.pid for n, s in self.children.items() if s.popen is not None and s.alive()}


def last_line(text: str) -> str:
    """The last non-empty line of `text`, stripped (for one-line error reports)."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else "(no output)"


def log_tail(path: Path, n: int = 15, indent: str = "") -> str:
    """The last `n` lines of a role's log, each prefixed with `indent` (for error reports)."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return f"{indent}(no log)"
    return "\n".join(indent + line for line in lines[-n:])


def _role_argv(sup: Supervised) -> list[str]:
    return [sys.executable, "-m", f"dvla.roles.{sup.proc.config.kind}", "--config", str(sup.config_path)]


def _close_stdin(sup: Supervised) -> None:
    if sup.popen is not None and sup.popen.stdin is not None:
        try:
            sup.popen.stdin.close()
        except OSError:
            pass


def _wait_listening(sup: Supervised, timeout_s: float) -> bool:
    """True once a TCP connection to one of `sup`'s ctrl listen endpoints succeeds."""
    addrs = [endpoint_address(locator) for locator in sup.proc.config.ctrl.listen]
    if not addrs:
        return True
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if sup.popen is not None and sup.popen.poll() is not None:
            return False  # it died; supervision will restart it
        for addr in addrs:
            try:
                with socket.create_connection(addr, timeout=0.5):
                    return True
            except OSError:
                pass
        time.sleep(0.1)
    return False


def busy_ports(processes: list[Process]) -> list[str]:
    """The listen endpoints of this host's processes that something else already holds, one line
    each: a second run of one topology on a machine (or a fixed ``base_port`` used twice) would
    otherwise join the first run's planes."""
    out = []
    for p in processes:
        if p.netns is not None or not is_local_host(p.host):
            continue  # bound inside a namespace, or on another host
        for plane in ("ctrl", "data"):
            for locator in getattr(p.config, plane).listen:
                host, port = endpoint_address(locator)
                with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as Zenoh binds: TIME_WAIT is no user
                    try:
                        s.bind((host, port))
                    except OSError as err:
                        if err.errno == errno.EADDRINUSE:
                            out.append(f"port {port} ({p.config.name}'s {plane} plane) is in use on this host "
                                       "(another run?): pass --base-port or change base_port")
    return out


def _signal(sup: Supervised, sig: int) -> None:
    # The child leads its own session: signal the group so helpers it spawned go too.
    killpg(sup.popen.pid, sig)  # type: ignore[union-attr]


def killpg(pid: int, sig: int) -> None:
    """Signal the process group led by `pid`, if it still exists."""
    try:
        os.killpg(pid, sig)
    except (ProcessLookupError, PermissionError):
        pass

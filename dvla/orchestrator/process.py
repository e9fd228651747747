"""What the orchestrator starts: the plan of a run's processes, each supervised process, and the
interface that runs a process elsewhere (a network namespace, an SSH host). It imports nothing
else of the orchestrator, so plan, launcher, netns and ssh share these types without importing each other.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from ..config import RoleConfig

_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Runs in a child between fork and exec: the kernel kills it when its parent dies."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except OSError:
        pass

LOOPBACK = "127.0.0.1"


def is_local_host(host: str) -> bool:
    """Whether `host` names this machine (its roles start here, not over SSH)."""
    return host in ("localhost", LOOPBACK, "::1", os.uname().nodename)


def endpoint_address(locator: str) -> tuple[str, int]:
    """(host, port) of a Zenoh locator such as ``tcp/10.77.0.10:17400`` or ``tls/[::1]:17400``."""
    host, _, port = locator.split("/", 1)[-1].rpartition(":")
    return host.strip("[]"), int(port)


@dataclass(frozen=True, kw_only=True)
class Process:
    """A process to start: its resolved config and where it runs."""

    config: RoleConfig
    host: str
    #: network namespace to run in (emulate: netns), else None
    netns: str | None = None


@dataclass(frozen=True, kw_only=True)
class Plan:
    """Every process of a run, in start order (actors, replicators, then leaves)."""

    processes: tuple[Process, ...]
    #: ctrl endpoints a tool (orchestrator, `dvla status`) connects to, nearest-to-root first
    ctrl_entry: tuple[str, ...]
    #: node name -> address its planes bind to
    addresses: dict[str, str]
    warnings: tuple[str, ...] = ()

    def by_name(self, name: str) -> Process:
        for p in self.processes:
            if p.config.name == name:
                return p
        raise KeyError(name)

    @property
    def root_actor(self) -> str:
        return next(p.config.name for p in self.processes if p.config.kind == "actor")


@dataclass
class Supervised:
    """One role process and its restart history."""

    proc: Process
    config_path: Path
    log_path: Path
    popen: subprocess.Popen | None = None
    restarts: int = 0
    exit_codes: list[int] = field(default_factory=list)
    next_start: float = 0.0
    started_at: float = 0.0
    failed: bool = False
    finished: bool = False

    @property
    def name(self) -> str:
        return self.proc.config.name

    def alive(self) -> bool:
        return self.popen is not None and self.popen.poll() is None


class CommandWrapper:
    """Turns a role's argv into one run elsewhere (a network namespace, an SSH host); this base
    runs it as is, here."""

    def __call__(self, proc: Process, argv: list[str]) -> list[str]:
        return argv

    def stdin_payload(self, proc: Process, argv: list[str], identity: str | None = None) -> bytes | None:
        """Bytes written to the process's stdin at start (None: stdin is /dev/null). `argv` is the
        unwrapped role command, `identity` its credential text. The pipe then stays open;
        closing it asks the process to stop."""
        return None

    def fork_into(self, proc: Process) -> str | None:
        """For a warm start (dvla/orchestrator/zygote.py): the network namespace a role forked on
        this host enters ("" for none), or None when the wrapped command cannot be a fork. A
        wrapper that changes the command says None unless it overrides this."""
        return "" if type(self).__call__ is CommandWrapper.__call__ else None

    def child_env(self, proc: Process, env: dict[str, str]) -> dict[str, str]:
        """The environment the launched command gets (a wrapper whose command would carry the
        environment elsewhere, as srun does, leaves the secrets out: they go on stdin)."""
        return env

    def output_path(self, sup: Supervised) -> Path | None:
        """File for the process's stdout (None: stdout and stderr both go to the role's log)."""
        return None

    def finished(self, sup: Supervised, code: int) -> str | None:
        """Called once the process has exited; returns an event line for the run's log, or None."""
        return None

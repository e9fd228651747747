"""Per-incarnation chunk counters that survive a `kill -9`: one small file per role process.

A killed process writes no summary, so what it produced, shipped or held when it died would
vanish from the run's accounting. Rollouts and the actor therefore keep their trajectory counters
in ``RUN_DIR/counters/<role>.<incarnation>.<pid>``, rewritten in place with one ``pwrite`` per
event. No fsync: the written pages belong to the kernel, which keeps them when the process dies
(only a host crash would lose them). The record is JSON padded with spaces to the longest record
written so far, so a reader never sees a shorter record's leftover tail.

Incarnations of one role never overlap in time (the launcher restarts a role after it exited),
so the n-th file of a role is its n-th incarnation. A rollout puts its incarnation in the high
bits of each chunk's ``seq`` (see :func:`split_seq`): the actor tells incarnations apart without
any new field on the wire, and ``seq`` stays strictly increasing across restarts.
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path
from typing import Any

COUNTERS_DIR = "counters"
#: low bits of a chunk's seq count chunks within one incarnation; the high bits are the incarnation
INCARNATION_SHIFT = 32


def split_seq(seq: int) -> tuple[int, int]:
    """(incarnation, chunk index within it) of a chunk's seq."""
    return seq >> INCARNATION_SHIFT, seq & ((1 << INCARNATION_SHIFT) - 1)


def source_key(rollout: str, seq: int) -> str:
    """``<rollout>#<incarnation>``: one rollout incarnation, as counter files name it."""
    return f"{rollout}#{seq >> INCARNATION_SHIFT}"


class CounterFile:
    """The counters of this process, rewritten whole on every `write` (thread-safe)."""

    def __init__(self, run_dir: str | Path, role: str) -> None:
        folder = Path(run_dir) / COUNTERS_DIR
        folder.mkdir(parents=True, exist_ok=True)
        self.incarnation = len(list(folder.glob(f"{role}.*")))
        while True:  # O_EXCL: a leftover of the same number is never overwritten
            self.path = folder / f"{role}.{self.incarnation}.{os.getpid()}"
            try:
                self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                break
            except FileExistsError:
                self.incarnation += 1
        self.role = role
        self.start_ns = time.time_ns()
        self._len = 0
        self._lock = threading.Lock()
        self._closed = False

    def write(self, doc: dict[str, Any]) -> None:
        record = {"role": self.role, "incarnation": self.incarnation, "pid": os.getpid(),
                  "start_ns": self.start_ns, "updated_ns": time.time_ns(), **doc}
        data = json.dumps(record, separators=(",", ":")).encode()
        with self._lock:
            if self._closed:
                return
            if len(data) < self._len:
                data = data.ljust(self._len)
            self._len = len(data)
            os.pwrite(self._fd, data, 0)

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                os.close(self._fd)


def read_counters(run_dir: str | Path) -> list[dict[str, Any]]:
    """Every counter record of a run (unreadable ones are reported with an ``error`` key)."""
    out = []
    for path in sorted((Path(run_dir) / COUNTERS_DIR).glob("*.*.*")):
        try:
            doc = json.loads(path.read_bytes().decode().strip() or "{}")
        except (OSError, ValueError) as err:
            doc = {"error": f"{path.name}: {err}"}
        doc["file"] = path.name
        out.append(doc)
    return out

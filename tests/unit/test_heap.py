"""keep_freed_buffers: MiB-sized buffers freed and taken again cost no new page faults.

Each case runs in a fresh interpreter (the settings are process-wide and cannot be undone) and
counts minor page faults over cycles shaped like a chunk's passage: two ~1 MiB buffers alive at
once, both freed.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from dvla.fabric.heap import DISABLE_ENV, keep_freed_buffers

glibc = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the settings are glibc's")

_CYCLES = """
import json, resource, sys
from dvla.fabric import keep_freed_buffers
kept = keep_freed_buffers()
def faults(n):
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        envelope = b"x" * (1 << 20)
        copy = envelope + b"tag"
        del envelope, copy
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / n
faults(4)
print(json.dumps({"kept": kept, "faults_per_cycle": faults(50)}))
"""


def _run(env_extra: dict[str, str]) -> dict[str, object]:
    env = {k: v for k, v in os.environ.items() if k not in (DISABLE_ENV, "GLIBC_TUNABLES")}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", _CYCLES], env=env, capture_output=True, text=True, timeout=60, check=True)
    return json.loads(out.stdout)


@glibc
def test_freed_buffers_are_reused_without_page_faults() -> None:
    got = _run({})
    assert got["kept"] is True
    assert got["faults_per_cycle"] < 16, got  # a 1 MiB buffer that were new memory would be 256


@glibc
def test_switched_off_leaves_glibc_defaults_which_fault_every_cycle() -> None:
    # the control: without the settings every cycle touches new pages (what the flood paid)
    got = _run({DISABLE_ENV: "0"})
    assert got["kept"] is False
    assert got["faults_per_cycle"] > 200, got


@glibc
def test_operator_tunables_win() -> None:
    got = _run({"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=0"})
    assert got["kept"] is False


def test_thresholds_must_be_positive() -> None:
    with pytest.raises(ValueError, match="thresholds must be > 0"):
        keep_freed_buffers(mmap_threshold=0)

"""Keep freed message-sized buffers in the process's heap instead of handing them back to the kernel.

Each trajectory or weight chunk a process sends or receives passes through fresh buffers of
hundreds of KiB to a few MiB: the envelope, Zenoh's copy of it, the received bytes. With glibc's
default settings malloc serves such a buffer with ``mmap`` or gives the top of the heap back with
``brk`` once two of them are free, so the next chunk's buffer is new memory again: one page fault
per 4 KiB, each page zeroed by the kernel. In the fabric bench (1 MiB chunks) that was 1.0-1.4 ms
of CPU per chunk in the sending process, ~40 % of what it spent per chunk (docs/benchmarks.md,
"Freed buffers kept"). Two ``mallopt`` settings keep that memory in the heap:
allocations below ``mmap_threshold`` come from the heap, and free memory at its top is returned
to the kernel only beyond ``trim_threshold``.

Every role process applies it at start (:func:`dvla.roles.runtime.main`); an embedding process
that moves chunks may call :func:`keep_freed_buffers` once at its start. The cost is memory held
back: at most ``trim_threshold`` of free heap per malloc arena stays in the process.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import platform

__all__ = ["DISABLE_ENV", "MMAP_THRESHOLD", "TRIM_THRESHOLD", "keep_freed_buffers"]

log = logging.getLogger("dvla.fabric.heap")

#: environment variable: "0" leaves glibc's malloc settings alone
DISABLE_ENV = "DVLA_KEEP_FREED_BUFFERS"
#: allocations below this come from the heap (glibc's largest accepted value on 64-bit hosts)
MMAP_THRESHOLD = 32 << 20
#: free memory at the top of a heap beyond this goes back to the kernel
TRIM_THRESHOLD = 128 << 20

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's malloc.h


def keep_freed_buffers(mmap_threshold: int = MMAP_THRESHOLD, trim_threshold: int = TRIM_THRESHOLD) -> bool:
    """Apply the two settings to this process; True when they are in force.

    False, and nothing changed, when ``DVLA_KEEP_FREED_BUFFERS=0``, when ``GLIBC_TUNABLES``
    already sets malloc tunables (the operator's choice wins), or when the C library is not glibc.
    """
    if mmap_threshold <= 0 or trim_threshold <= 0:
        raise ValueError(f"thresholds must be > 0, got mmap {mmap_threshold}, trim {trim_threshold}")
    if os.environ.get(DISABLE_ENV, "1").strip() == "0":
        return False
    if "glibc.malloc." in os.environ.get("GLIBC_TUNABLES", ""):
        return False
    if platform.libc_ver()[0] != "glibc":  # other C libraries' mallopt take other options
        return False
    mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, mmap_threshold) == 1 and mallopt(_M_TRIM_THRESHOLD, trim_threshold) == 1
    if not ok:
        log.warning("mallopt refused mmap_threshold=%d / trim_threshold=%d: glibc defaults kept in part",
                    mmap_threshold, trim_threshold)
    return ok

"""One Python thread state per Zenoh receive thread, kept for the thread's life.

zenoh-python runs a ``Callback(..., indirect=False)`` handler on Zenoh's own (Rust) threads.
Such a thread has no Python thread state, so every call into Python creates one and deletes it
on the way out (``PyGILState_Ensure``/``Release`` with a count that drops back to zero), and the
new state's first frame maps a fresh frame stack: per message, an allocation, a page mapping
and its page faults, and the teardown. For a 64 KiB trajectory chunk that was 15-25 µs of the
receiving process's CPU per message, more than the fabric's decode.

:func:`hold` takes one extra ``PyGILState_Ensure`` on the calling thread, the first time it runs
there, and never releases it: the thread keeps its state, and later callbacks reuse it. The GIL
itself is still released after every callback (the extra count only keeps the state alive).

At interpreter exit, CPython frees every thread state (``Py_Finalize``); a Zenoh thread that
calls into Python after that point exits on taking the GIL, before it touches its state, exactly
as a thread with no state does: holding changes nothing there.
"""

from __future__ import annotations

import ctypes
import threading

_here = threading.local()
_ensure = ctypes.pythonapi.PyGILState_Ensure


def hold() -> None:
    """Keep this thread's Python thread state from now on (cheap after the first call)."""
    if not getattr(_here, "held", False):
        _ensure()
        _here.held = True

"""Starts a thread at import: a process that imports it must not fork (tests/unit/test_zygote.py)."""

import threading

threading.Thread(target=threading.Event().wait, daemon=True, name="probe-idle").start()

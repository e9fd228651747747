"""A stand-in role for tests/unit/test_zygote.py: reports what process it runs as, then exits
with the code it is given (or sleeps until killed)."""

import json
import os
import sys
import time

out, code = sys.argv[1], int(sys.argv[2])
print(f"probe {os.getpid()} says hello", flush=True)
with open(out, "w") as f:
    json.dump({"argv": sys.argv[1:], "env": os.environ.get("PROBE_VALUE"), "pid": os.getpid(),
               "pgid": os.getpgid(0), "sid": os.getsid(0), "name": __name__, "stdin": sys.stdin.read(),
               "cmdline": open("/proc/self/cmdline", "rb").read().replace(b"\0", b" ").decode()}, f)
if code < 0:
    time.sleep(600)
raise SystemExit(code)

"""Free TCP ports for runs started programmatically (benchmarks, tests) beside other runs."""

from __future__ import annotations

import socket


def free_port_block(n: int = 8) -> int:
    """A base port whose next ``n`` ports are free right now (other runs may share the machine)."""
    for _ in range(100):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base + n >= 65000:
            continue
        socks: list[socket.socket] = []
        try:
            for p in range(base, base + n):
                t = socket.socket()
                socks.append(t)
                t.bind(("127.0.0.1", p))
            return base
        except OSError:
            continue
        finally:
            for t in socks:
                t.close()
    raise RuntimeError("no block of free TCP ports on 127.0.0.1")

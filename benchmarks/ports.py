"""Free TCP ports for runs started programmatically (benchmarks, tests) beside other runs."""

from __future__ import annotations

import random
import socket
from pathlib import Path

#: not the `random` module's generator: a seed a caller sets must not make two processes agree
_RANDOM = random.SystemRandom()


def free_port_block(n: int = 8) -> int:
    """A base port whose next ``n`` ports are free right now (other runs may share the machine).

    Chosen below the kernel's ephemeral range: a port from it (``bind(0)``) is where outgoing
    connections of every process on the machine take their local ports, so one could take the
    run's listen port between this check and the role binding it. (Above 20000: clear of the
    topologies' own ``base_port``.)"""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    for _ in range(200):
        base = _RANDOM.randrange(20000, max(20001, low - n))
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

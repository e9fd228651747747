"""A bare Zenoh router (what a site runs at its edge): listens on LISTEN, connects to CONNECT.

usage: router.py LISTEN CONNECT  (runs until killed)
"""

from __future__ import annotations

import json
import sys
import time

import zenoh


def main() -> None:
    listen, connect = sys.argv[1:3]
    conf = zenoh.Config()
    for key, value in (("mode", "router"), ("listen/endpoints", [listen]), ("connect/endpoints", [connect]),
                       ("scouting/multicast/enabled", False), ("scouting/gossip/enabled", False)):
        conf.insert_json5(key, json.dumps(value))
    with zenoh.open(conf):
        print("ready", flush=True)
        while True:
            time.sleep(1.0)


if __name__ == "__main__":
    main()

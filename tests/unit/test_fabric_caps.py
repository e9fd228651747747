"""Tests of dvla.fabric.Fabric's send caps: an envelope over the plane's max_message_size, which
every receiver of the run would drop while reassembling it, is not sent and is counted."""

from __future__ import annotations

import numpy as np

from dvla.fabric import Fabric, TrajectoryChunk, plane_config
from dvla.fabric.messages import Command


def _chunk(name: str, n_obs: int) -> TrajectoryChunk:
    f = np.zeros((1, 1), np.float32)
    b = np.zeros((1, 1), bool)
    return TrajectoryChunk(rollout=name, seq=0, policy_version=0, env_steps=1,
                           obs={"state": np.zeros((1, 1, n_obs), np.float32)}, actions=np.zeros((1, 1, 1), np.float32),
                           logprobs=f, rewards=f, terminated=b, truncated=b, success=b,
                           next_obs={"state": np.zeros((1, n_obs), np.float32)},
                           final_obs={"state": np.zeros((1, 1, n_obs), np.float32)})


def test_envelopes_over_the_plane_cap_are_counted_not_sent():
    cap = 64 << 10
    conf = lambda: plane_config(mode="peer", listen=("tcp/127.0.0.1:0",), max_message_size=cap)  # noqa: E731
    fabric = Fabric(run="caps", name="r0", ctrl_conf=conf(), data_conf=conf(), secret=b"k" * 32)
    try:
        assert fabric.send_cap == {"ctrl": cap, "data": cap}
        assert fabric.publish_traj(_chunk("r0", 8)) > 0
        assert fabric.publish_traj(_chunk("r0", cap // 4)) == 0  # ~3 x 64 KiB of obs
        big = Command(target="all", verb="stop", args={"x": np.zeros(cap, np.uint8)}, issued_ns=0)
        assert fabric.publish_ctrl(fabric.keys.cmd("all"), big) == 0
        snap = fabric.accounting.snapshot()
        assert fabric.accounting.get("data", "dropped.oversize") == 1
        assert fabric.accounting.get("ctrl", "dropped.oversize") == 1
        assert fabric.accounting.get("data", "sent") == 1, snap
    finally:
        fabric.close()

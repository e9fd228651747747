"""dvla.fabric.zconfig: the receive cap on Zenoh messages reaches the config, and sizes for it."""

from __future__ import annotations

import json

import pytest
import zenoh

from dvla.fabric.messages import ArraySpec, ChunkSpec
from dvla.fabric.zconfig import (
    BLOCK_WAIT_BEFORE_CLOSE_US,
    DATA_BLOCK_WAIT_BEFORE_CLOSE_US,
    MAX_MESSAGE_SIZE_KEY,
    plane_config,
    plane_max_message_size,
)


def test_max_message_size_is_carried_and_a_session_opens_with_it() -> None:
    default = json.loads(plane_config().get_json(MAX_MESSAGE_SIZE_KEY))
    assert default == 1 << 30  # Zenoh's own default, untouched without the argument
    conf = plane_config(mode="peer", listen=["tcp/127.0.0.1:0"], max_message_size=3 << 20)
    assert json.loads(conf.get_json(MAX_MESSAGE_SIZE_KEY)) == 3 << 20
    session = zenoh.open(conf)
    try:
        assert str(session.zid())
    finally:
        session.close()
    for bad in (0, -1, 1.5, True, "1MiB"):
        with pytest.raises(ValueError, match="max_message_size"):
            plane_config(max_message_size=bad)  # type: ignore[arg-type]


def test_plane_max_message_size_from_declared_sizes() -> None:
    # tiny state task: 25 steps x 2 envs, 42 float32 obs, 8 actions
    chunk = ChunkSpec(obs={"state": ArraySpec((42,), "float32")}, act_dim=8, T=25, N=2).nbytes()
    assert chunk == 25 * 2 * (2 * 168 + 32 + 8 + 3) + 2 * 168
    assert plane_max_message_size(chunk) == 1 << 20  # small runs get the floor
    big = ChunkSpec(obs={"rgb": ArraySpec((64, 64, 3), "uint8")}, act_dim=8, T=50, N=64).nbytes()
    assert plane_max_message_size(big) == int(big * 1.25) + (64 << 10) < 1 << 30
    with pytest.raises(ValueError):
        plane_max_message_size(-1)


def test_each_plane_says_how_long_a_blocked_put_may_wait_before_its_link_is_closed() -> None:
    key = "transport/link/tx/queue/congestion_control/block/wait_before_close"
    assert json.loads(plane_config().get_json(key)) == BLOCK_WAIT_BEFORE_CLOSE_US == 30_000_000
    data = plane_config(block_close_us=DATA_BLOCK_WAIT_BEFORE_CLOSE_US)
    assert json.loads(data.get_json(key)) == 10_000_000

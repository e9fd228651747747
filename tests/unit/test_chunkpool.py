"""The rollout's ChunkPool: preallocated chunks filled in place, encoded by the one codec, reused."""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
import pytest

from dvla.fabric import TrajectoryChunk, decode, encode
from dvla.roles.chunkpool import ChunkPool, chunk_template


class _Spec:
    def __init__(self, shape: tuple[int, ...], dtype: type) -> None:
        self.shape, self.dtype = shape, np.dtype(dtype)


SPEC = {"state": _Spec((5,), np.float32), "rgb": _Spec((4, 4, 3), np.uint8)}


def template(T: int = 3, n: int = 2) -> TrajectoryChunk:
    return chunk_template("rollout-0", T, n, SPEC, act_dim=4)


def fill(m: TrajectoryChunk, seed: int) -> dict[str, np.ndarray]:
    """Write random data into the arrays of `m` in place, step by step as the sim lane does."""
    rng = np.random.default_rng(seed)
    want = {
        "state": rng.standard_normal(m.obs["state"].shape, dtype=np.float32),
        "rgb": rng.integers(0, 256, m.obs["rgb"].shape, dtype=np.uint8),
        "actions": rng.standard_normal(m.actions.shape, dtype=np.float32),
        "success": rng.random(m.success.shape) < 0.5,
        "next_state": rng.standard_normal(m.next_obs["state"].shape, dtype=np.float32),
    }
    for t in range(m.actions.shape[0]):
        m.obs["state"][t] = want["state"][t]
        m.obs["rgb"][t] = want["rgb"][t]
        m.actions[t] = want["actions"][t]
        m.success[t] = want["success"][t]
    m.next_obs["state"][...] = want["next_state"]
    return want


@pytest.mark.parametrize("seq", [0, 1, 127, 2**32 + 5, 2**64 - 1])
def test_a_pooled_chunk_filled_in_place_round_trips_with_its_per_chunk_fields(seq: int) -> None:
    pool = ChunkPool(template(), size=2)
    chunk = pool.take(threading.Event())
    want = fill(chunk, seed=seq % 1000)
    sent = dataclasses.replace(chunk, seq=seq, policy_version=7, created_ns=1_700_000_000_123_456_789)
    got = decode(encode(sent), expect=TrajectoryChunk)
    assert (got.seq, got.policy_version, got.created_ns) == (seq, 7, 1_700_000_000_123_456_789)
    assert got.rollout == "rollout-0" and got.env_steps == 6
    np.testing.assert_array_equal(got.obs["state"], want["state"])
    np.testing.assert_array_equal(got.obs["rgb"], want["rgb"])
    np.testing.assert_array_equal(got.actions, want["actions"])
    np.testing.assert_array_equal(got.success, want["success"])
    np.testing.assert_array_equal(got.next_obs["state"], want["next_state"])
    assert got.obs["rgb"].dtype == np.uint8 and got.success.dtype == np.bool_


def test_a_reused_chunk_carries_each_new_fill() -> None:
    pool = ChunkPool(template(), size=1)
    for i in range(3):
        chunk = pool.take(threading.Event())
        want = fill(chunk, seed=i)
        raw = encode(dataclasses.replace(chunk, seq=i))
        pool.give(chunk)
        fill(chunk, seed=100 + i)  # refilled after the encode: the bytes sent are unaffected
        got = decode(raw, expect=TrajectoryChunk)
        assert got.seq == i
        np.testing.assert_array_equal(got.actions, want["actions"])


def test_chunk_pool_hands_out_each_chunk_once_and_stops_waiting_on_stop() -> None:
    pool = ChunkPool(template(), size=3)
    stop = threading.Event()
    taken = [pool.take(stop) for _ in range(3)]
    assert len({id(b) for b in taken}) == 3 and pool.free() == 0
    # every chunk has arrays of its own (and none shares the template's)
    assert len({id(b.actions) for b in taken}) == 3 and len({id(b.obs["rgb"]) for b in taken}) == 3
    taken[0].actions[...] = 1.0
    assert not taken[1].actions.any()
    stop_timer = threading.Timer(0.2, stop.set)
    stop_timer.start()
    t0 = time.monotonic()
    assert pool.take(stop) is None  # every chunk is out: waits, then gives up on stop
    assert 0.15 < time.monotonic() - t0 < 2.0
    stop_timer.join()
    pool.give(taken[1])
    assert pool.take(threading.Event()) is taken[1]
    with pytest.raises(ValueError):
        ChunkPool(template(), size=0)

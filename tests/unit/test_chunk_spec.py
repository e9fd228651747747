"""ChunkSpec, the one description of a trajectory chunk's arrays: the chunks it allocates are
what the codec and the learner's check accept; a rollout's pool of them is filled in place,
encoded by the one codec and reused."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from dvla.fabric import TrajectoryChunk, decode, encode
from dvla.fabric.messages import ArraySpec, ChunkSpec, chunk_arrays
from dvla.roles.freelist import FreeList

SPEC = ChunkSpec(obs={"state": ArraySpec((5,), "float32"), "rgb": ArraySpec((4, 4, 3), "uint8")}, act_dim=4,
                 extras={"bins": ArraySpec((4,), "int32", vocab=8)}, T=3, N=2)


def pool(size: int) -> FreeList[TrajectoryChunk]:
    """A rollout group's chunks, allocated once."""
    return FreeList(SPEC.zeros() for _ in range(size))


def test_zeros_is_a_chunk_of_the_spec_for_any_env_count_up_to_N() -> None:
    for n in (1, 2):
        c = SPEC.zeros(n)
        assert (c.horizon, c.num_envs, c.env_steps) == (3, n, 3 * n)
        assert {p: (a.shape, a.dtype.name) for p, a in chunk_arrays(c).items()} == {
            p: (shape, s.dtype) for p, (shape, s) in SPEC.layout(n).items()}
        assert not any(a.any() for a in chunk_arrays(c).values())
        assert SPEC.nbytes(n) == sum(a.nbytes for a in chunk_arrays(c).values())  # what the data plane's cap counts
        c.validate()  # the wire's check: the arrays agree with each other
        assert SPEC.problem(c) is None  # the learner's: they are what the run declared
        implied = ChunkSpec.implied_by(c)  # what the wire sees: shapes and dtypes, no vocabularies
        assert (implied.obs, implied.act_dim, implied.T, implied.N) == (SPEC.obs, 4, 3, n)
    assert SPEC.problem(ChunkSpec(obs=SPEC.obs, act_dim=4, extras=SPEC.extras, T=3, N=3).zeros())[0] == "shape"


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
    chunk = pool(2).take(threading.Event())
    want = fill(chunk, seed=seq % 1000)
    sent = dataclasses.replace(chunk, seq=seq, policy_version=7, created_ns=1_700_000_000_123_456_789)
    got = decode(encode(sent), expect=TrajectoryChunk)
    assert (got.seq, got.policy_version, got.created_ns) == (seq, 7, 1_700_000_000_123_456_789)
    assert got.rollout == "" and got.env_steps == 6
    np.testing.assert_array_equal(got.obs["state"], want["state"])
    np.testing.assert_array_equal(got.obs["rgb"], want["rgb"])
    np.testing.assert_array_equal(got.actions, want["actions"])
    np.testing.assert_array_equal(got.success, want["success"])
    np.testing.assert_array_equal(got.next_obs["state"], want["next_state"])
    assert got.obs["rgb"].dtype == np.uint8 and got.success.dtype == np.bool_


def test_a_reused_chunk_carries_each_new_fill() -> None:
    chunks = pool(1)
    for i in range(3):
        chunk = chunks.take(threading.Event())
        want = fill(chunk, seed=i)
        raw = encode(dataclasses.replace(chunk, seq=i))
        chunks.give(chunk)
        fill(chunk, seed=100 + i)  # refilled after the encode: the bytes sent are unaffected
        got = decode(raw, expect=TrajectoryChunk)
        assert got.seq == i
        np.testing.assert_array_equal(got.actions, want["actions"])


def test_chunk_pool_hands_out_each_chunk_once_and_stops_waiting_on_stop() -> None:
    chunks = pool(3)
    stop = threading.Event()
    taken = [chunks.take(stop) for _ in range(3)]
    assert len({id(b) for b in taken}) == 3 and chunks.free() == 0
    # every chunk has arrays of its own: what is written into one is in no other
    taken[0].actions[...] = 1.0
    taken[0].obs["rgb"][...] = 7
    assert not taken[1].actions.any() and not taken[2].obs["rgb"].any()
    got: list[object] = []
    waiter = threading.Thread(target=lambda: got.append(chunks.take(stop)), daemon=True)
    waiter.start()
    waiter.join(timeout=0.2)
    assert waiter.is_alive() and got == []  # every chunk is out: it waits ...
    stop.set()
    waiter.join(timeout=30)
    assert not waiter.is_alive() and got == [None]  # ... then gives up on stop
    chunks.give(taken[1])
    assert chunks.take(threading.Event()) is taken[1]

"""The chunk ledger across kills (dvla/ledger.py): reconciliation of counter files written as
the roles write them, for the cases a run can
produce: clean, a killed rollout, a killed actor, a silent mid-stream loss, forged trajectories."""

from __future__ import annotations

import json
from pathlib import Path

from dvla.ledger import INCARNATION_SHIFT, CounterFile, read_counters, reconcile, source_key, split_seq

T0 = 1_000_000_000_000


def _rollout(run: Path, name: str, inc: int, produced: int, shipped: int, clean: bool, t: tuple[int, int]) -> None:
    doc = {"role": name, "incarnation": inc, "pid": 100 + inc, "start_ns": T0 + t[0], "updated_ns": T0 + t[1],
           "kind": "rollout", "produced": produced, "shipped": shipped, "bytes": shipped * 4000, "queue_cap": 8,
           "clean": clean}
    (run / "counters").mkdir(parents=True, exist_ok=True)
    (run / "counters" / f"{name}.{inc}.{100 + inc}").write_text(json.dumps(doc))


def _actor(run: Path, inc: int, sources: dict, clean: bool, t: tuple[int, int], fabric: dict | None = None) -> None:
    doc = {"role": "actor", "incarnation": inc, "pid": 200 + inc, "start_ns": T0 + t[0], "updated_ns": T0 + t[1],
           "kind": "actor", "sources": sources, "fabric": fabric or {}, "inbox_cap": 64, "slots": 20, "clean": clean}
    (run / "counters").mkdir(parents=True, exist_ok=True)
    (run / "counters" / f"actor.{inc}.{200 + inc}").write_text(json.dumps(doc))


def _src(got: int, first: int, last: int, **settled: int) -> dict:
    return {"got": got, "first": first, "last": last, **{k.replace("__", "."): v for k, v in settled.items()}}


def test_counter_file_survives_rewrites_and_names_incarnations(tmp_path: Path) -> None:
    a = CounterFile(tmp_path, "rollout-x")
    a.write({"kind": "rollout", "produced": 123456, "clean": False})
    a.write({"kind": "rollout", "produced": 7, "clean": False})  # shorter record: no stale tail
    b = CounterFile(tmp_path, "rollout-x")  # the next incarnation (the first one was "killed")
    b.write({"kind": "rollout", "produced": 1, "clean": True})
    docs = {d["incarnation"]: d for d in read_counters(tmp_path)}
    assert docs[0]["produced"] == 7 and docs[1]["produced"] == 1 and b.incarnation == 1
    seq = (1 << INCARNATION_SHIFT) + 5
    assert split_seq(seq) == (1, 5) and source_key("rollout-x", seq) == "rollout-x#1"


def test_clean_run_closes_with_nothing_lost(tmp_path: Path) -> None:
    _rollout(tmp_path, "r", 0, 10, 10, True, (0, 100))
    _actor(tmp_path, 0, {"r#0": _src(10, 0, 9, consumed=8, dropped__stale=1, dropped__shutdown=1)}, True, (0, 101))
    acct = reconcile(tmp_path)
    assert acct["produced"] == 10 and acct["consumed"] == 8 and acct["dropped"] == 2
    assert acct["lost"] == 0 and acct["unaccounted"] == 0


def test_killed_rollout_loses_its_tail_within_bound(tmp_path: Path) -> None:
    _rollout(tmp_path, "r", 0, 20, 15, False, (0, 50))  # killed: 5 in its queue, 2 in transit
    _rollout(tmp_path, "r", 1, 10, 10, True, (60, 100))
    _actor(tmp_path, 0, {"r#0": _src(13, 0, 12, consumed=13), "r#1": _src(10, 0, 9, consumed=10)}, True, (0, 101))
    acct = reconcile(tmp_path)
    (lost,) = acct["lost_by_incarnation"]
    assert (lost["role"], lost["incarnation"], lost["lost"], lost["in_queue"], lost["in_transit"]) == ("r", 0, 7, 5, 2)
    assert acct["lost_within_bounds"] and acct["unaccounted"] == 0
    assert acct["produced"] == acct["consumed"] + acct["dropped"] + acct["rejected"] + acct["lost"]


def test_killed_actor_accounts_its_slots_and_the_gap(tmp_path: Path) -> None:
    _rollout(tmp_path, "r", 0, 30, 30, True, (0, 100))
    # actor 0 got 0..11, settled 9 (3 died in its slots); 12..14 died in transit; actor 1 got 15..29
    _actor(tmp_path, 0, {"r#0": _src(12, 0, 11, consumed=9)}, False, (0, 40))
    _actor(tmp_path, 1, {"r#0": _src(15, 15, 29, consumed=15)}, True, (45, 101))
    acct = reconcile(tmp_path)
    (lost,) = acct["lost_by_incarnation"]
    assert (lost["where"], lost["in_actor"], lost["in_transit"], lost["lost"]) == ("actor", 3, 3, 6)
    assert acct["unaccounted"] == 0 and acct["lost_within_bounds"]
    assert acct["produced"] == 30 == acct["consumed"] + acct["lost"]


def test_silent_mid_stream_loss_is_unaccounted(tmp_path: Path) -> None:
    _rollout(tmp_path, "r", 0, 10, 10, True, (0, 100))
    _actor(tmp_path, 0, {"r#0": _src(8, 0, 9, consumed=8)}, True, (0, 101))  # two vanished, nobody killed
    acct = reconcile(tmp_path)
    assert acct["unaccounted"] == 2 and acct["notes"] == ["r.0.100: 2 chunks missing mid-stream"]


def test_chunks_of_a_rollout_without_counter_file_are_named(tmp_path: Path) -> None:
    _rollout(tmp_path, "r", 0, 4, 4, True, (0, 100))
    # "q" left no file (its host never sent its results back): its chunks are in no one's produced
    _actor(tmp_path, 0, {"r#0": _src(4, 0, 3, consumed=4), "q#0": _src(2, 0, 1, consumed=2)}, True, (0, 101))
    acct = reconcile(tmp_path)
    assert acct["unaccounted"] == -2 and acct["notes"][0] == "chunks of q#0 received, but it left no counter file"


def test_fabric_drops_explain_gaps_and_forgeries_are_foreign(tmp_path: Path) -> None:
    _rollout(tmp_path, "r", 0, 10, 10, True, (0, 100))
    fabric = {"r": {"received": 30, "rejected": 21, "backpressure": 1}}  # 1 dropped, 21 undecodable (20 forged)
    _actor(tmp_path, 0, {"r#0": _src(8, 0, 9, consumed=8)}, True, (0, 101), fabric)
    acct = reconcile(tmp_path)
    assert acct["dropped_by_reason"] == {"backpressure": 1} and acct["rejected_by_reason"] == {"undecodable": 1}
    assert acct["foreign_rejected"] == 20 and acct["unaccounted"] == 0


def test_an_unreadable_counter_file_is_named(tmp_path: Path) -> None:
    _rollout(tmp_path, "r", 0, 3, 3, True, (0, 100))
    _actor(tmp_path, 0, {"r#0": _src(3, 0, 2, consumed=3)}, True, (0, 101))
    (tmp_path / "counters" / "r.1.777").write_bytes(b'{"role": "r", "kind": "rol')  # cut short
    acct = reconcile(tmp_path)
    assert acct["unaccounted"] == 0 and len(acct["notes"]) == 1 and acct["notes"][0].startswith("r.1.777: ")

"""`dvla bench fabric`'s figures from what it measured: each formula fed known raw figures (no
process, no session, no clock), so that what the bench reports is checked exactly whatever this
machine's speed; the figures themselves are `dvla bench fabric`'s to report."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import pytest

from benchmarks import fabric as bench
from benchmarks.fabric import HEADLINE_KEYS, BenchConfig, Layout, _Pair

#: (target bytes, auth mode) -> the rounds of one throughput pair: (bytes/s, pub CPU us/chunk, sub CPU us/chunk)
ROUNDS: dict[tuple[int, str], list[tuple[float, float, float]]] = {
    (64 * 1024, "identity"): [(6.4e6, 10.0, 20.0), (12.8e6, 30.0, 40.0), (3.2e6, 20.0, 5.0)],
    (1024 * 1024, "identity"): [(2e8, 100.0, 300.0), (1e8, 200.0, 100.0), (3e8, 150.0, 200.0)],
    (256 * 1024, "none"): [(2e6, 10.0, 20.0), (4e6, 30.0, 40.0), (3e6, 20.0, 30.0)],
    (256 * 1024, "tag"): [(1e6, 25.0, 35.0), (2e6, 15.0, 25.0), (1.5e6, 35.0, 45.0)],
    # identity cheaper than none: a difference of measured CPU is reported as it came out, negative too
    (256 * 1024, "identity"): [(3e6, 5.0, 20.0), (1e6, 15.0, 30.0), (2e6, 10.0, 25.0)],
}

#: (layout, shared session, flood, auth, ctrl apart) -> (idle p99, loaded p99) in ms
P99: dict[tuple[str, bool, str, str, str], tuple[float | None, float]] = {
    ("loopback", False, "fabric", "identity", ""): (2.0, 5.0),
    ("loopback", True, "fabric", "identity", ""): (None, 8.0),
    ("links", False, "fabric", "identity", ""): (1.0, 4.0),
    ("links", True, "fabric", "identity", ""): (None, 6.0),
    ("links", False, "fabric", "none-data", ""): (1.0, 3.0),
    ("links", False, "tcp", "identity", ""): (0.5, 1.5),
    ("links", False, "fabric", "identity", "processes"): (1.25, 2.5),
    ("links", False, "fabric", "identity", "core"): (1.0, 1.5),
    ("links", False, "cpu", "identity", ""): (0.8, 2.0),
}
#: the CPU the sink and source burned in the loaded phase (cores); with the ctrl path apart, their flood's own
FLOOD_CORES = {"": 1.5, "processes": 0.75, "core": 0.5}


class FakePair:
    """A throughput pair whose rounds are :data:`ROUNDS`."""

    def __init__(self, ctx: Any, n: int, target: int, cfg: BenchConfig, secret: bytes, auth: str = "identity",
                 rounds: int | None = None) -> None:
        self.rounds, self.size, self.lost = ROUNDS[(target, auth)], target, 0

    def start(self, pids: list[int]) -> None:
        pass

    def round(self, r: int) -> tuple[float, float, float]:
        return self.rounds[r]

    def stop(self) -> None:
        pass


class FakeLinks:
    """The links layout, without namespaces."""

    sink_ns, source_ns = "ns-sink", "ns-source"

    def __enter__(self) -> Layout:
        return Layout("links", sink_ns=self.sink_ns, source_ns=self.source_ns, gbit=1.0)

    def __exit__(self, *exc: object) -> None:
        pass


def fake_ctrl(ctx: Any, layout: Layout, shared: bool, cfg: BenchConfig, secret: bytes, pids: list[int], *,
              idle: bool, flood_kind: str = "fabric", auth: str = "identity", hog_cores: float = 0.0,
              apart: str = "") -> dict[str, Any]:
    """One ctrl RTT measurement, its p99s from :data:`P99`."""
    idle_p99, loaded_p99 = P99[(layout.name, shared, flood_kind, auth, apart)]
    loaded = {"samples": 10, "p50_ms": loaded_p99 / 2, "p99_ms": loaded_p99, "flood": flood_kind, "auth": auth,
              "apart": apart, "flood_bytes_per_s": 0.0 if flood_kind == "cpu" else 1e8,
              "flood_cpu_cores": FLOOD_CORES[apart]}
    if flood_kind == "cpu":
        loaded.update(hog_cores_asked=hog_cores, hog_cores=hog_cores)
    out: dict[str, Any] = {"loaded": loaded, "cpus": {}}
    if idle:
        assert idle_p99 is not None
        out["idle"] = {"samples": 10, "p50_ms": idle_p99 / 2, "p99_ms": idle_p99}
        out["block_ratios"] = [loaded_p99 / idle_p99 / 2, 3 * loaded_p99 / idle_p99 / 2]
    return out


@pytest.fixture
def bench_doc(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """`run_bench`'s document over the fakes, with the links layout and both ctrl-apart controls."""
    monkeypatch.setattr(bench, "_Pair", FakePair)
    monkeypatch.setattr(bench, "_measure_ctrl", fake_ctrl)
    monkeypatch.setattr(bench, "_weights_auth_cost", lambda secret: {"tag": {}, "identity": {}})
    monkeypatch.setattr(bench, "links_available", lambda: None)
    monkeypatch.setattr(bench, "TwoLinks", FakeLinks)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})  # two CPUs: the "core" control too
    return bench.run_bench(dataclasses.replace(BenchConfig.quick(), rounds=3))


def test_throughput_figures_are_the_medians_of_the_rounds(bench_doc: dict[str, Any]) -> None:
    e = bench_doc["throughput"]["64k"]
    assert e["rounds_bytes_per_s"] == [6.4e6, 12.8e6, 3.2e6]
    assert e["bytes_per_s"] == 6.4e6 and e["chunks_per_s"] == 6.4e6 / (64 * 1024)
    assert (e["pub_cpu_us_per_msg"], e["sub_cpu_us_per_msg"]) == (20.0, 20.0)
    assert bench_doc["chunks_per_s_64k"] == e["chunks_per_s"] and bench_doc["mb_per_s_64k"] == pytest.approx(6.4)
    assert bench_doc["chunks_per_s_1m"] == 2e8 / (1024 * 1024) and bench_doc["mb_per_s_1m"] == pytest.approx(200.0)


def test_auth_figures_are_ratios_and_differences_to_the_pair_without_envelopes(bench_doc: dict[str, Any]) -> None:
    data = bench_doc["auth"]["data"]
    size = 256 * 1024
    assert data["none"]["chunks_per_s"] == 3e6 / size and data["none"]["rounds_chunks_per_s"] == [x / size for x in (2e6, 4e6, 3e6)]
    assert (data["none"]["pub_cpu_us_per_chunk"], data["none"]["sub_cpu_us_per_chunk"]) == (20.0, 30.0)
    assert data["tag"]["throughput_ratio"] == pytest.approx(1.5e6 / 3e6)
    assert data["tag"]["extra_cpu_us_per_chunk"] == (25.0 + 35.0) - (20.0 + 30.0)
    assert data["identity"]["throughput_ratio"] == pytest.approx(2e6 / 3e6)
    assert data["identity"]["extra_cpu_us_per_chunk"] == (10.0 + 25.0) - (20.0 + 30.0) == -15.0
    assert bench_doc["auth_throughput_ratio"] == data["identity"]["throughput_ratio"]
    assert bench_doc["auth_extra_cpu_us_per_chunk"] == -15.0
    assert bench_doc["actor_cpu_us_per_auth_chunk"] == 25.0


def test_ctrl_figures_are_ratios_of_the_phases_p99s(bench_doc: dict[str, Any]) -> None:
    doc = bench_doc
    assert doc["links_layout"] == "used" and doc["ctrl_rtt_layout"] == "links" and doc["netns"] == ["ns-sink", "ns-source"]
    assert (doc["ctrl_rtt_p99_idle_ms"], doc["ctrl_rtt_p99_loaded_ms"], doc["ctrl_rtt_p99_loaded_shared_ms"]) == (1.0, 4.0, 6.0)
    assert doc["loaded_over_idle"] == 4.0 and doc["shared_over_separate"] == 1.5
    assert doc["loaded_over_idle_blocks"] == {"median": 4.0, "min": 2.0, "max": 6.0, "values": [2.0, 6.0]}
    assert doc["noauth_loaded_over_idle"] == 3.0 and doc["tcp_flood_over_idle"] == 3.0
    assert doc["apart_processes_over_idle"] == 2.0 and doc["apart_core_over_idle"] == 1.5
    # the CPU control burns the flood's own CPU: the sink's and source's with the ctrl path apart
    assert doc["flood_cpu_cores"] == 0.75 and doc["ctrl_rtt"]["loaded_cpu"]["hog_cores_asked"] == 0.75
    assert doc["cpu_load_over_idle"] == pytest.approx(2.5)
    assert doc["ctrl_rtt_layouts"]["loopback"]["loaded"]["p99_ms"] == 5.0  # measured, not the headline
    assert all(k in doc for k in HEADLINE_KEYS)


def test_a_round_divides_what_was_taken_and_burned_by_its_chunks(monkeypatch: pytest.MonkeyPatch) -> None:
    """`_Pair.round`: bytes/s from the publisher's first put to the consumer's last chunk, and the
    CPU microseconds per chunk of each side (the subscriber's since the end of its last round)."""
    messages = {"pub": ("pub", 0, 10.0, 0.02), "sub": ("sub", 0, 12.0, 5.5, 100, {})}
    monkeypatch.setattr(bench, "_collect", lambda out, wanted, timeout_s: {w: messages[w] for w in wanted})

    class Queue:
        def put(self, item: object) -> None:
            pass

    pair = _Pair.__new__(_Pair)
    pair.n, pair.size, pair.cfg, pair.sent, pair.taken, pair.sub_cpu_mark = 100, 1000, BenchConfig.quick(), 0, 0, 5.0
    pair.go = pair.told = Queue()
    pair.out = None
    rate, pub_us, sub_us = pair.round(0)
    assert rate == 100 * 1000 / (12.0 - 10.0)
    assert pub_us == pytest.approx(0.02 / 100 * 1e6) and sub_us == pytest.approx((5.5 - 5.0) / 100 * 1e6)
    assert pair.sub_cpu_mark == 5.5 and pair.lost == 0

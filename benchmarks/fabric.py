"""`dvla bench fabric`: what the message fabric costs, and what its separate ctrl session buys.

Everything runs in one invocation on this machine with Zenoh shared memory off, every role in
its own process (multiprocessing, spawn) so that the cores are used as in a real run:

* **Throughput** (TCP on loopback). Trajectory chunks of about 64 KiB and 1 MiB through the
  trajectory path as a rollout and an actor use it (what each side does per chunk is spelled
  out in :data:`DOES` and copied into the JSON): chunks/s and bytes/s from the publisher's
  first put to the consumer's last chunk, and each side's CPU time per chunk; the median of
  the rounds. A round ends when every chunk sent has arrived, or when the publisher is done and
  nothing has arrived for `IDLE_S`: chunks that never came are reported as `lost`.
* **Ctrl latency.** RTT of a signed status request/reply (`Fabric.query` -> `Fabric.serve`)
  from a tool process, through the sink's ctrl router, to a source process: idle; while the
  source floods its data session with 1 MiB chunks to the sink (the real layout of a rollout
  feeding an actor, with the reply crossing the flooded direction); and, as the baseline, the
  same flood with data and ctrl forced onto one shared session and link. Idle and flooded
  samples are taken in alternating blocks (the flood drained before each idle block), so that
  background load changes hit both alike; percentiles are over the pooled samples. Measured in two
  layouts (:class:`Layout`): `loopback`, where the data link's capacity is the CPU, and, where
  root can build it, `links`: two network namespaces with one rate-limited veth link per plane,
  so that the flood fills the data link while the CPU still has room, as between real hosts.
  The headline figures come from `links` when it ran. Its controls, same run: the flood without
  envelopes; the link flooded by plain TCP; the ctrl path (router, status responder) moved into
  processes that carry no trajectories, then also pinned to a CPU the flood does not use
  (:data:`APART`); and the flood's own CPU burned with no traffic (:data:`FLOODS`).

Every loop is bounded both in count and in time; a worker that does not report in time fails
the bench instead of hanging it, and the namespaces are removed whatever happens.
"""
from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import queue
import resource
import shutil
import socket
import statistics
import subprocess
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable

import numpy as np

from .stats import percentile, process_cpu_s

log = logging.getLogger("dvla.bench.fabric")

RUN = "bench"
SOURCE, SINK, TOOL = "bench-source", "bench-sink", "bench-tool"
PROBE_KEY = "bench/probe"
KIB, MIB = 1 << 10, 1 << 20
#: seconds a worker may take to start (imports, session open) before the bench fails
START_TIMEOUT_S = 30.0


@dataclass(frozen=True)
class BenchConfig:
    """Counts of one bench run (`quick` shrinks them to check the machinery, not the speed)."""

    #: messages per throughput round, 64 KiB chunks
    n_64k: int = 6000
    #: messages per throughput round, 1 MiB chunks
    n_1m: int = 300
    #: throughput rounds per configuration (the median is reported)
    rounds: int = 9
    #: RTT samples per phase
    rtt_samples: int = 1000
    #: idle and loaded samples are taken in this many alternating blocks, so that a change of
    #: background load between the two phases hits both alike
    rtt_blocks: int = 4
    #: wall-clock cap of one throughput round or one RTT phase, seconds
    phase_timeout_s: float = 20.0
    #: flood the data plane this long before sampling loaded RTTs, seconds
    warmup_s: float = 1.0

    @staticmethod
    def quick() -> "BenchConfig":
        return BenchConfig(n_64k=40, n_1m=8, rounds=1, rtt_samples=20, rtt_blocks=2, phase_timeout_s=15.0,
                           warmup_s=0.3)


# --------------------------------------------------------------------------------------------
# shared helpers (imported by the spawned workers too)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def make_chunk(name: str, target_bytes: int) -> Any:
    """A TrajectoryChunk whose encoding is about `target_bytes` (a float32 state observation)."""
    from dvla.fabric import TrajectoryChunk

    T, N, A = 16, 4, 8
    rng = np.random.default_rng(0)
    # obs and final_obs are [T, N, D], next_obs [N, D]; the small arrays and keys take ~2 KB.
    D = max(1, (target_bytes - 2 * KIB) // (4 * (2 * T + 1) * N))
    obs = rng.standard_normal((T, N, D), dtype=np.float32)
    return TrajectoryChunk(
        rollout=name, seq=0, policy_version=1, env_steps=T * N,
        obs={"state": obs}, actions=rng.standard_normal((T, N, A), dtype=np.float32),
        logprobs=np.zeros((T, N), np.float32), rewards=np.ones((T, N), np.float32),
        terminated=np.zeros((T, N), bool), truncated=np.zeros((T, N), bool), success=np.zeros((T, N), bool),
        next_obs={"state": obs[-1].copy()}, final_obs={"state": np.zeros_like(obs)},
    )


def payload_size(target_bytes: int) -> int:
    """Bytes per message: the encoded chunk."""
    from dvla.fabric import encode

    return len(encode(make_chunk(SOURCE, target_bytes)))


def _cpu_s() -> float:
    """CPU seconds used so far by this whole process (every thread, Zenoh's included)."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _direct(callback: Callable[[Any], None]) -> Any:
    """A subscriber callback run on Zenoh's receive thread, as the fabric's data inbox's is."""
    import zenoh

    try:
        return zenoh.handlers.Callback(callback, indirect=False)
    except TypeError:
        return callback


def _probe_subscriber(session: Any, routed: Any) -> Any:
    """Declared after the subscriber under test: once a probe arrives, that one is known too."""
    return session.declare_subscriber(PROBE_KEY, _direct(lambda _s: routed.set()))


def _probe_until_routed(session: Any, routed: Any, timeout_s: float) -> None:
    # Publisher.matching_status can read True between peers before the remote subscriber is
    # known (puts are then lost): probe end to end instead.
    deadline = time.monotonic() + timeout_s
    while not routed.is_set():
        if time.monotonic() > deadline:
            raise TimeoutError("no route from the publisher to the subscriber")
        session.put(PROBE_KEY, b"probe")
        routed.wait(0.02)


#: how the throughput pair authenticates trajectory chunks (the auth phase compares them)
AUTH_MODES = ("none", "tag", "identity")


class _PassThrough:
    """Baseline of the auth phase only: an envelope that is the bare payload, accepted as is."""

    def seal(self, key: str, payload: Any, *, bind: bytes = b"") -> bytes:
        return bytes(payload)

    def __init__(self, kind: str = "") -> None:
        self.kind = kind  # what every opened envelope claims to be sent by

    def open(self, key: str, envelope: Any, **_kw: Any) -> Any:
        from dvla.fabric.keys import KeySpace
        from dvla.fabric.signing import Opened

        return Opened(KeySpace.last(key), self.kind, memoryview(envelope), b"")


class _DataPassThrough:
    """Trajectory keys without envelopes, every other key through `real` (a signer or verifier)."""

    def __init__(self, real: Any, traj_prefix: str) -> None:
        self._real, self._prefix, self._none = real, traj_prefix, _PassThrough("rollout")

    def seal(self, key: str, payload: Any, **kw: Any) -> bytes:
        return (self._none if key.startswith(self._prefix) else self._real).seal(key, payload, **kw)

    def open(self, key: str, envelope: Any, **kw: Any) -> Any:
        return (self._none if key.startswith(self._prefix) else self._real).open(key, envelope, **kw)


def _open_fabric(name: str, secret: bytes, *, ctrl: Any, data: Any = None, shared: bool = False,
                 auth: str = "identity", identity: str | None = None) -> Any:
    """A bench fabric; `auth` "identity" (as under `dvla up`: the run secret's tag and the sender's
    certified Ed25519 signature, `identity` its credential text), "tag" (the run secret only),
    "none", or "none-data" (trajectories without envelopes, control as under `dvla up`)."""
    from dvla.fabric import CTRL, DATA, Fabric, keep_freed_buffers
    from dvla.fabric.identity import Identity

    keep_freed_buffers()  # as every role process does (DVLA_KEEP_FREED_BUFFERS=0: glibc's defaults)
    ident = Identity.from_text(identity) if auth in ("identity", "none-data") and identity else None
    fabric = Fabric(run=RUN, name=name, ctrl_conf=ctrl, data_conf=None if shared else data, secret=secret,
                    identity=ident)
    if auth == "none":
        fabric._signer = fabric._verifier = _PassThrough()
    elif auth == "none-data":
        prefix = fabric.keys.traj_all().rstrip("*")
        fabric._signer = _DataPassThrough(fabric._signer, prefix)
        fabric._verifier = _DataPassThrough(fabric._verifier, prefix)
    if shared:
        # Baseline only: both planes on one session, hence one link per peer.
        fabric.data = fabric.ctrl
        fabric.send_cap = {**fabric.send_cap, DATA: fabric.send_cap[CTRL]}  # the one session's cap
    return fabric


# --------------------------------------------------------------------------------------------
# throughput workers


def _between_rounds_s(phase_timeout_s: float) -> float:
    """How long a worker waits for its next round (the first waits for the pair to start)."""
    return START_TIMEOUT_S + 2 * phase_timeout_s


class Arrivals:
    """Chunks a subscriber has taken, counted as they come; a round ends when every chunk sent
    has arrived, or, once the publisher is done, when nothing has arrived for `idle_s` (a chunk
    lost on the way then ends the round as a loss, not as a stall)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.count = 0
        self.last = time.monotonic()

    def add(self) -> None:
        with self._cond:
            self.count += 1
            self.last = time.monotonic()
            self._cond.notify_all()

    def wait_for(self, sent: int, idle_s: float) -> tuple[int, float]:
        """Once `sent` chunks have been sent in all: (chunks taken in all, when the last came)."""
        told = time.monotonic()
        with self._cond:
            while self.count < sent and time.monotonic() - max(self.last, told) < idle_s:
                self._cond.wait(0.05)
            return self.count, self.last


#: a round whose publisher is done ends after this long without an arrival (what is missing is lost)
IDLE_S = 3.0


def _throughput_sub(port: int, rounds: int, secret: bytes, ready: Any, routed: Any, sent: Any, out: Any,
                    timeout_s: float, auth: str = "identity", identity: str | None = None) -> None:
    """Takes chunks from a trajectory inbox; after each round, told how many were sent in all,
    reports how many it has taken in all, when the last one was taken, and its CPU time by then."""
    from dvla.fabric import TrajectoryChunk, plane_config

    fabric = _open_fabric(SINK, secret, ctrl=plane_config(), data=plane_config(mode="peer", listen=[endpoint(port)]),
                          auth=auth, identity=identity)
    arrivals = Arrivals()
    stop = threading.Event()

    def consume() -> None:  # as the actor's ingest lane takes chunks
        while not stop.is_set():
            if inbox.get(timeout=0.5) is not None:
                arrivals.add()

    try:
        inbox = fabric.subscribe_traj(maxsize=64, expect=TrajectoryChunk)
        consumer = threading.Thread(target=consume, name="consumer")
        consumer.start()
        probe = _probe_subscriber(fabric.data, routed)
        try:
            out.put(("sub_ready", 0, 0.0, _cpu_s()))
            ready.set()
            for r in range(rounds):
                total = sent.get(timeout=_between_rounds_s(timeout_s))
                if total is None:
                    return
                got, last = arrivals.wait_for(total, IDLE_S)
                out.put(("sub", r, last, _cpu_s(), got, fabric.accounting.snapshot()))
        except queue.Empty:
            out.put(("error", "the subscriber was never told what the publisher sent"))
        finally:
            probe.undeclare()
            stop.set()
            consumer.join()
    finally:
        fabric.close()


def _throughput_pub(port: int, n: int, rounds: int, target: int, secret: bytes, routed: Any, go: Any, out: Any,
                    timeout_s: float, auth: str = "identity", identity: str | None = None) -> None:
    """Sends `n` chunks per round, each round when told; reports when each round started."""
    import dataclasses

    from dvla.fabric import plane_config

    fabric = _open_fabric(SOURCE, secret, ctrl=plane_config(), data=plane_config(mode="peer", connect=[endpoint(port)]),
                          auth=auth, identity=identity)
    chunk = make_chunk(SOURCE, target)
    try:
        _probe_until_routed(fabric.data, routed, timeout_s)
        seq = 0
        for r in range(rounds):
            if go.get(timeout=_between_rounds_s(timeout_s)) is None:
                return
            t0, c0 = time.monotonic(), _cpu_s()
            for _ in range(n):
                # as a rollout ships a chunk whose arrays it filled in place
                fabric.publish_traj(dataclasses.replace(chunk, seq=seq, created_ns=time.time_ns()))
                seq += 1
            out.put(("pub", r, t0, _cpu_s() - c0))
    finally:
        fabric.close()


#: what each side of a throughput round does per chunk (also written into the JSON)
DOES = ("publisher: as a rollout ships a chunk: Fabric.publish_traj of a TrajectoryChunk (validate, encode, "
        "BLOCK put, accounting); subscriber: Fabric.subscribe_traj, on Zenoh's receive thread: copies the payload "
        "out as Python bytes, accounts, decodes and validates it zero-copy into a TrajectoryChunk and hands it to "
        "the bounded inbox; a consumer thread takes every chunk from the inbox, as the actor's ingest lane does")


class _Pair:
    """A subscriber and a publisher process, driven round by round."""

    def __init__(self, ctx: Any, n: int, target: int, cfg: BenchConfig, secret: bytes, auth: str = "identity",
                 rounds: int | None = None) -> None:
        from dvla.fabric.identity import Identity

        self.n, self.size, self.cfg = n, payload_size(target), cfg
        self.rounds = rounds or cfg.rounds
        #: chunks sent and taken in all, over the rounds so far
        self.sent = self.taken = 0
        port = free_port()
        self.ready, self.routed, self.out, self.go = ctx.Event(), ctx.Event(), ctx.Queue(), ctx.Queue()
        self.told = ctx.Queue()  # to the subscriber: chunks sent in all, once a round is sent
        t = cfg.phase_timeout_s
        op = Identity.operator(RUN)  # as `dvla up` issues them: the sink acts as the actor
        ids = (op.issue("actor", SINK).to_text(), op.issue("rollout", SOURCE).to_text())
        self.sub = ctx.Process(target=_throughput_sub, args=(port, self.rounds, secret, self.ready, self.routed, self.told,
                                                             self.out, t, auth, ids[0]))
        self.pub = ctx.Process(target=_throughput_pub, args=(port, n, self.rounds, target, secret, self.routed, self.go,
                                                             self.out, t, auth, ids[1]))

    @property
    def lost(self) -> int:
        """Chunks sent that the subscriber never took (late ones count once they arrive)."""
        return self.sent - self.taken

    def start(self, pids: list[int]) -> None:
        self.sub.start()
        pids.append(self.sub.pid)
        _wait_event(self.ready, self.sub, "subscriber")
        self.sub_cpu_mark = _collect(self.out, {"sub_ready"}, 5)["sub_ready"][3]  # after its start-up
        self.pub.start()
        pids.append(self.pub.pid)
        _wait_event(self.routed, self.pub, "publisher route")

    def round(self, r: int) -> tuple[float, float, float]:
        """Round `r`: bytes/s of the chunks taken, from the publisher's first put to the
        consumer's last chunk, and the CPU time per chunk (µs, all threads, Zenoh's included) of
        publisher and subscriber."""
        self.go.put(r)
        pub = _collect(self.out, {"pub"}, self.cfg.phase_timeout_s + 5)["pub"]
        self.sent += self.n
        self.told.put(self.sent)
        sub = _collect(self.out, {"sub"}, self.cfg.phase_timeout_s + IDLE_S + 5)["sub"]
        taken, self.taken = sub[4] - self.taken, sub[4]
        if self.lost:
            log.warning("throughput round %d: %d of %d chunks lost so far (subscriber's counters: %s)",
                        r, self.lost, self.sent, sub[5])
        # The subscriber's CPU between the ends of two of its rounds: it idles in between.
        sub_cpu = sub[3] - self.sub_cpu_mark
        self.sub_cpu_mark = sub[3]
        rate = taken * self.size / max(sub[2] - pub[2], 1e-9)
        return rate, pub[3] / self.n * 1e6, sub_cpu / max(taken, 1) * 1e6

    def stop(self) -> None:
        self.go.put(None)
        self.told.put(None)
        _stop([self.sub, self.pub])


def _measure_auth(ctx: Any, cfg: BenchConfig, secret: bytes, pids: list[int]) -> dict[str, Any]:
    """The cost of authentication. Data plane: three throughput pairs (no envelope, the secret's
    tag only, tag + identity signature) on 256 KiB chunks, their rounds interleaved; medians, CPU per chunk
    and the ratios to the unauthenticated pair. Weights: sealing and opening one 64 MiB version
    in 1 MiB chunks, in this process, tag only and with identities."""
    target, n, rounds = 256 * KIB, max(cfg.n_64k // 4, 50), cfg.rounds
    pairs = {mode: _Pair(ctx, n, target, cfg, secret, auth=mode, rounds=rounds) for mode in AUTH_MODES}
    got: dict[str, list[tuple[float, float, float]]] = {m: [] for m in AUTH_MODES}
    try:
        for pair in pairs.values():
            pair.start(pids)
        for r in range(rounds):
            for mode, pair in pairs.items():
                got[mode].append(pair.round(r))
    finally:
        for pair in pairs.values():
            pair.stop()
    data = {}
    for mode, rs in got.items():
        bps = statistics.median(x[0] for x in rs)
        data[mode] = {"chunks_per_s": bps / pairs[mode].size, "pub_cpu_us_per_chunk": statistics.median(x[1] for x in rs),
                      "sub_cpu_us_per_chunk": statistics.median(x[2] for x in rs),
                      "rounds_chunks_per_s": [x[0] / pairs[mode].size for x in rs], "lost": pairs[mode].lost}
    base = data["none"]
    for mode in ("tag", "identity"):
        d = data[mode]
        d["throughput_ratio"] = d["chunks_per_s"] / base["chunks_per_s"]
        d["extra_cpu_us_per_chunk"] = (d["pub_cpu_us_per_chunk"] + d["sub_cpu_us_per_chunk"]
                                       - base["pub_cpu_us_per_chunk"] - base["sub_cpu_us_per_chunk"])
    return {"chunk_bytes": pairs["none"].size, "chunks_per_round": n, "rounds": rounds, "data": data,
            "weights": _weights_auth_cost(secret)}


def _weights_auth_cost(secret: bytes, version_bytes: int = 64 * MIB, chunk: int = MIB, repeats: int = 3) -> dict[str, Any]:
    """CPU seconds to seal and to open (verify) every chunk envelope of one weight version."""
    from dvla.fabric.identity import Identity
    from dvla.fabric.keys import KeySpace
    from dvla.fabric.signing import Signer, Verifier

    keys = KeySpace(RUN)
    key = keys.weights_signed()
    payload = os.urandom(chunk)
    op = Identity.operator(RUN)
    out: dict[str, Any] = {"version_bytes": version_bytes, "chunk_bytes": chunk}
    for mode, ident in (("tag", None), ("identity", op.issue("actor", SINK))):
        signer = Signer(secret, SINK, identity=ident)
        seal_s, open_s = [], []
        for _ in range(repeats):
            verifier = Verifier(secret, run=RUN, operator=op.public if ident else None)
            c0 = time.process_time()
            envs = [signer.seal(key, payload) for _ in range(version_bytes // chunk)]
            c1 = time.process_time()
            for env in envs:
                verifier.open(key, env)
            seal_s.append(c1 - c0)
            open_s.append(time.process_time() - c1)
        out[mode] = {"seal_cpu_s": statistics.median(seal_s), "open_cpu_s": statistics.median(open_s)}
    return out


def _measure_throughput(ctx: Any, n: int, target: int, cfg: BenchConfig, secret: bytes, pids: list[int]) -> dict[str, Any]:
    """`cfg.rounds` rounds of `n` chunks; the median of each figure over the rounds."""
    pair = _Pair(ctx, n, target, cfg, secret)
    try:
        pair.start(pids)
        rounds = [pair.round(r) for r in range(cfg.rounds)]
    finally:
        pair.stop()
    bps = statistics.median(r[0] for r in rounds)
    return {"payload_bytes": pair.size, "messages": n, "lost": pair.lost, "bytes_per_s": bps,
            "chunks_per_s": bps / pair.size,
            "rounds_bytes_per_s": [r[0] for r in rounds], "does": DOES,
            "pub_cpu_us_per_msg": statistics.median(r[1] for r in rounds),
            "sub_cpu_us_per_msg": statistics.median(r[2] for r in rounds)}


# --------------------------------------------------------------------------------------------
# ctrl latency: where the processes run


@dataclass(frozen=True)
class Layout:
    """Where the sink (actor) and source (rollout) of the ctrl RTT phases listen and run.

    `loopback`: all on 127.0.0.1; both planes' links are TCP over the host's loopback, whose
    capacity is the CPU. `links`: two network namespaces joined by two veth links, one per
    plane, each limited to `gbit` by a token bucket: the data link has a capacity the flood can
    fill while the CPU still has room (as between real hosts), and the ctrl link is the separate
    path the design gives the control plane (distinct addresses/NICs per plane).
    """

    name: str
    #: network namespace of the sink and the tool, and of the source (None: this one)
    sink_ns: str | None = None
    source_ns: str | None = None
    #: the sink's address on the data link and on the ctrl link
    data_addr: str = "127.0.0.1"
    ctrl_addr: str = "127.0.0.1"
    #: link rate (links layout), Gbit/s
    gbit: float | None = None

    def describe(self) -> str:
        if self.gbit is None:
            return "loopback TCP (no link limit: the CPU is the data plane's capacity)"
        return (f"two network namespaces, one veth link per plane ({self.gbit:g} Gbit/s token bucket each "
                "direction); the shared-session baseline puts both planes on the data link")


LOOPBACK = Layout("loopback")
LINK_GBIT = 1.0
_DATA_NET, _CTRL_NET = "10.98.1", "10.98.2"


class TwoLinks:
    """Creates (and always removes) the `links` layout; needs root and iproute2."""

    def __init__(self, gbit: float = LINK_GBIT) -> None:
        tag = f"dvfb{os.getpid() % 100000}"
        self.sink_ns, self.source_ns = f"{tag}-snk", f"{tag}-src"
        self.gbit = gbit
        self.layout = Layout("links", sink_ns=self.sink_ns, source_ns=self.source_ns,
                             data_addr=f"{_DATA_NET}.2", ctrl_addr=f"{_CTRL_NET}.2", gbit=gbit)

    def __enter__(self) -> Layout:
        from dvla.orchestrator.netns import ip, rate_limit

        try:
            for ns in (self.source_ns, self.sink_ns):
                ip("netns", "add", ns)
                ip("link", "set", "lo", "up", ns=ns)
            for i, net in enumerate((_DATA_NET, _CTRL_NET)):
                # veth pair created in the source namespace, one end moved to the sink's
                ip("link", "add", f"l{i}", "type", "veth", "peer", "name", f"p{i}", ns=self.source_ns)
                ip("link", "set", f"p{i}", "netns", self.sink_ns, ns=self.source_ns)
                for ns, dev, host in ((self.source_ns, f"l{i}", 1), (self.sink_ns, f"p{i}", 2)):
                    ip("addr", "add", f"{net}.{host}/24", "dev", dev, ns=ns)
                    ip("link", "set", dev, "up", ns=ns)
                    rate_limit(ns, dev, self.gbit)
        except BaseException:
            self.__exit__()
            raise
        return self.layout

    def __exit__(self, *exc: object) -> None:
        for ns in (self.source_ns, self.sink_ns):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)


def links_available() -> str | None:
    """None when the `links` layout can be built here, else why not."""
    if os.geteuid() != 0:
        return "needs root (network namespaces)"
    if shutil.which("ip") is None or shutil.which("tc") is None:
        return "needs iproute2 (ip, tc)"
    return None


def _enter_ns(ns: str | None) -> None:
    """Move this (fresh, single-threaded) worker process into `ns` before it opens sockets."""
    if ns is not None:
        from dvla.orchestrator.netns import enter_netns

        enter_netns(ns)


# --------------------------------------------------------------------------------------------
# ctrl latency workers


def _status_reply() -> Any:
    from dvla.fabric import RoleStatus

    return RoleStatus(name=SOURCE, kind="rollout", node="bench", rack="bench", pid=os.getpid(), state="running",
                      policy_version=1, env_steps=0, steps_per_s=0.0)


def _ctrl_addr(layout: Layout, shared: bool) -> str:
    # The shared-session baseline runs both planes over the data link (one link, as a topology
    # without plane separation would); the separate ctrl session has a link of its own.
    return layout.data_addr if shared else layout.ctrl_addr


#: what loads a loaded ctrl RTT phase: the source's trajectory chunks through its data session
#: ("fabric"); as controls, plain TCP from the same process over the same link ("tcp": no Zenoh,
#: no envelopes, no Python per byte: the delay the flooded link and this machine's kernel add by
#: themselves), or no traffic at all, only processes burning the CPU the fabric's flood added to
#: the sink's and source's ("cpu", `hog_cores`: how much of the isolation loss is the CPU, not
#: the planes)
FLOODS = ("fabric", "tcp", "cpu")
#: processes that share the CPU control's load (each busy for `hog_cores / HOGS` of the time)
HOGS = 2
#: where the ctrl path runs in a ctrl RTT phase: "" as under `dvla up` (the sink's process is the
#: ctrl router, the source's answers the status queries); "processes": a router and a status
#: responder in processes of their own, so that no process on the ctrl path carries trajectories
#: (the sink and source keep ctrl sessions, as clients of that router); "core": the same, with
#: the ctrl path's processes (router, responder, tool) pinned to one CPU and the sink and source
#: to the others: the ctrl path with CPU that the flood does not compete for
APART = ("", "processes", "core")


def split_cpus() -> tuple[set[int], set[int]]:
    """(one CPU for the ctrl path, the others for the flood) of this process's CPUs, for the
    "core" control; RuntimeError with fewer than two."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        raise RuntimeError(f"the ctrl-on-a-core control needs two CPUs, this process may use {cpus}")
    return {cpus[0]}, set(cpus[1:])


def _cpu_hog(flood: Any, stop: Any, duty: float, max_s: float) -> None:
    """Burn `duty` of one core in 1 ms slices while `flood` is set (no network, no Zenoh)."""
    deadline = time.monotonic() + max_s
    while not stop.is_set() and time.monotonic() < deadline:
        if not flood.wait(0.1):
            continue
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 1e-3 * duty:
            pass
        time.sleep(1e-3 * (1.0 - duty))


def _proc_cpu_s(pids: list[int]) -> float:
    """User + system CPU seconds of live processes so far."""
    return sum(x for x in map(process_cpu_s, pids) if x is not None)


def _tcp_drain(sock: socket.socket, received: Any, received_bytes: Any, stop: Any) -> None:
    """The "tcp" flood's receiving end: counts every MiB read."""
    sock.settimeout(0.5)
    conn = None
    while conn is None and not stop.is_set():
        try:
            conn, _ = sock.accept()
        except TimeoutError:
            continue
    if conn is None:
        return
    buf, pending = bytearray(MIB), 0
    with conn:
        conn.settimeout(0.5)
        while not stop.is_set():
            try:
                n = conn.recv_into(buf)
            except TimeoutError:
                continue
            if not n:
                return
            pending += n
            while pending >= MIB:
                pending -= MIB
                received.value += 1
                received_bytes.value += MIB


def _rtt_sink(layout: Layout, shared: bool, ctrl_port: int, data_port: int, secret: bytes, ready: Any, stop: Any,
              received: Any, received_bytes: Any, max_s: float, identity: str, flood: str, tcp_port: int,
              auth: str, apart: bool, cpus: set[int] | None) -> None:
    """The actor's side: ctrl router (the tool and the source attach to it; `apart`: a client of
    :func:`_ctrl_apart`'s router instead) and the traj inbox."""
    _pin(cpus)
    _enter_ns(layout.sink_ns)
    from dvla.fabric import DATA, TrajectoryChunk, plane_config

    ctrl_at = f"tcp/{_ctrl_addr(layout, shared)}:{ctrl_port}"
    fabric = _open_fabric(
        SINK, secret, shared=shared, identity=identity, auth=auth,
        ctrl=plane_config(mode="client", connect=[ctrl_at]) if apart else plane_config(mode="router", listen=[ctrl_at]),
        data=plane_config(mode="peer", listen=[f"tcp/{layout.data_addr}:{data_port}"]),
    )
    drain = None
    try:
        inbox = fabric.subscribe_traj(maxsize=64, expect=TrajectoryChunk)
        if flood == "tcp":
            listener = socket.create_server((layout.data_addr, tcp_port))
            drain = threading.Thread(target=_tcp_drain, args=(listener, received, received_bytes, stop), name="tcp-drain")
            drain.start()
        ready.set()
        deadline = time.monotonic() + max_s
        while not stop.is_set() and time.monotonic() < deadline:
            if inbox.get(timeout=0.1) is not None:
                received.value += 1  # this process is the only writer
                received_bytes.value = fabric.accounting.get(DATA, "received_bytes")
    finally:
        stop.set()
        if drain is not None:
            drain.join()
        fabric.close()


def _rtt_source(layout: Layout, shared: bool, ctrl_port: int, data_port: int, secret: bytes, ready: Any, flood: Any,
                stop: Any, max_s: float, max_msgs: int, identity: str, kind: str, tcp_port: int, auth: str,
                apart: bool, cpus: set[int] | None) -> None:
    """The rollout's side: answers status queries (`apart`: :func:`_ctrl_apart`'s responder does);
    floods 1 MiB chunks (of `kind`, :data:`FLOODS`) while `flood` is set."""
    _pin(cpus)
    _enter_ns(layout.source_ns)
    from dvla.fabric import plane_config

    fabric = _open_fabric(
        SOURCE, secret, shared=shared, identity=identity, auth=auth,
        ctrl=plane_config(mode="client", connect=[f"tcp/{_ctrl_addr(layout, shared)}:{ctrl_port}"]),
        data=plane_config(mode="peer", connect=[f"tcp/{layout.data_addr}:{data_port}"]),
    )
    try:
        if not apart:
            fabric.serve(fabric.keys.status(SOURCE), lambda _req: _status_reply())
        chunk = make_chunk(SOURCE, MIB)
        raw = socket.create_connection((layout.data_addr, tcp_port), timeout=START_TIMEOUT_S) if kind == "tcp" else None
        block = bytes(MIB)
        ready.set()
        deadline = time.monotonic() + max_s
        sent = 0
        while not stop.is_set() and time.monotonic() < deadline and sent < max_msgs:
            if kind == "cpu":  # the CPU control answers status queries and sends nothing
                stop.wait(0.1)
                continue
            if not flood.wait(0.1):
                continue
            if raw is not None:
                raw.sendall(block)
            else:
                fabric.publish_traj(chunk)
            sent += 1
        if raw is not None:
            raw.close()
    finally:
        fabric.close()


def _rtt_tool(layout: Layout, shared: bool, ctrl_port: int, secret: bytes, cmds: Any, out: Any,
              timeout_s: float, identity: str, auth: str, cpus: set[int] | None) -> None:
    """`dvla status`'s side, next to the sink: samples RTTs of signed status queries on demand
    (as the operator, who alone may ask)."""
    _pin(cpus)
    _enter_ns(layout.sink_ns)
    from dvla.fabric import plane_config

    tool = _open_fabric(TOOL, secret, identity=identity, auth=auth,
                        ctrl=plane_config(mode="client", connect=[f"tcp/{_ctrl_addr(layout, shared)}:{ctrl_port}"]))
    try:
        key = tool.keys.status(SOURCE)
        try:
            _wait_reachable(tool, key)
        except RuntimeError as err:
            out.put(("error", str(err)))
            return
        out.put(("reachable",))
        while True:
            cmd = cmds.get(timeout=START_TIMEOUT_S + 4 * timeout_s)
            if cmd is None:
                return
            phase, n = cmd
            out.put((phase, _sample_rtts(tool, key, n, timeout_s)))
    finally:
        tool.close()


def _ctrl_apart(layout: Layout, which: str, ctrl_port: int, secret: bytes, identity: str | None, ready: Any, stop: Any,
                max_s: float, cpus: set[int] | None) -> None:
    """A process of the "apart" controls' ctrl path, carrying no trajectories: `which` "router",
    the ctrl router in the sink's namespace (a fabric with only a ctrl session, in router mode,
    as dvla's router role is); "responder", in the source's namespace, a client of that router
    answering the tool's signed status queries for the source (`identity`: the source's)."""
    _pin(cpus)
    router = which == "router"
    _enter_ns(layout.sink_ns if router else layout.source_ns)
    from dvla.fabric import plane_config

    at = f"tcp/{layout.ctrl_addr}:{ctrl_port}"
    fabric = _open_fabric("bench-router" if router else SOURCE, secret, identity=identity,
                          ctrl=plane_config(mode="router", listen=[at]) if router else plane_config(mode="client", connect=[at]))
    try:
        if not router:
            fabric.serve(fabric.keys.status(SOURCE), lambda _req: _status_reply())
        ready.set()
        stop.wait(max_s)
    finally:
        fabric.close()


def _pin(cpus: set[int] | None) -> None:
    """Restrict this (fresh, single-threaded) worker to `cpus` before it starts any thread
    (threads inherit the mask of the thread that creates them); None: leave it alone."""
    if cpus is not None:
        os.sched_setaffinity(0, cpus)


def _sample_rtts(tool: Any, key: str, n: int, timeout_s: float) -> tuple[list[float], int]:
    """(RTTs in ms of answered queries, number of unanswered ones)."""
    rtts: list[float] = []
    misses = 0
    deadline = time.monotonic() + timeout_s
    while len(rtts) + misses < n and time.monotonic() < deadline:
        t0 = time.perf_counter()
        replies = tool.query(key, timeout=2.0)
        dt = (time.perf_counter() - t0) * 1e3
        if replies:
            rtts.append(dt)
        else:
            misses += 1
    return rtts, misses


def _summary(rtts: list[float], misses: int, what: str) -> dict[str, Any]:
    if not rtts:
        raise RuntimeError(f"no reply to any status query ({what})")
    rtts = sorted(rtts)
    return {"samples": len(rtts), "timeouts": misses, "p50_ms": percentile(rtts, 50), "p99_ms": percentile(rtts, 99),
            "max_ms": rtts[-1]}


def _measure_ctrl(ctx: Any, layout: Layout, shared: bool, cfg: BenchConfig, secret: bytes, pids: list[int], *,
                  idle: bool, flood_kind: str = "fabric", auth: str = "identity", hog_cores: float = 0.0,
                  apart: str = "") -> dict[str, Any]:
    """Idle (optional) and loaded RTT phases against one sink/source pair, every process with the
    identity `dvla up` would give it (sink: actor, source: rollout, tool: operator); `auth`
    "none-data": the flood without envelopes (the baseline of what authenticating it costs the ctrl plane).
    The loaded phase reports the CPU the sink and source burned (`flood_cpu_cores`: CPU seconds
    per second; with `apart`, where they answer no queries, the flood's own CPU);
    `flood_kind` "cpu" loads the machine with :data:`HOGS` processes burning `hog_cores` in all
    instead of any traffic; `apart` (:data:`APART`) moves the ctrl path out of the sink and
    source. The result's `cpus` is each process's CPU affinity, by name."""
    from dvla.fabric.identity import Identity

    if flood_kind not in FLOODS:
        raise ValueError(f"flood_kind {flood_kind!r}: expected one of {FLOODS}")
    if apart not in APART or (apart and shared):
        raise ValueError(f"apart {apart!r}: expected one of {APART}, and none with one shared session")
    ctrl_cpus, flood_cpus = split_cpus() if apart == "core" else (None, None)
    op = Identity.operator(RUN)
    ctrl_port, data_port, tcp_port = free_port(), free_port(), free_port()
    if shared:
        data_port = ctrl_port  # one session: it listens once
    ready_sink, ready_src, flood, stop = ctx.Event(), ctx.Event(), ctx.Event(), ctx.Event()
    received, received_bytes = ctx.Value("q", 0), ctx.Value("q", 0)
    cmds, out = ctx.Queue(), ctx.Queue()
    max_s = 4 * cfg.phase_timeout_s + 30
    sink = ctx.Process(target=_rtt_sink, args=(layout, shared, ctrl_port, data_port, secret, ready_sink, stop, received,
                                               received_bytes, max_s, op.issue("actor", SINK).to_text(), flood_kind,
                                               tcp_port, auth, bool(apart), flood_cpus))
    src = ctx.Process(target=_rtt_source, args=(layout, shared, ctrl_port, data_port, secret, ready_src, flood, stop,
                                                max_s, 1_000_000, op.issue("rollout", SOURCE).to_text(), flood_kind,
                                                tcp_port, auth, bool(apart), flood_cpus))
    tool = ctx.Process(target=_rtt_tool, args=(layout, shared, ctrl_port, secret, cmds, out, cfg.phase_timeout_s,
                                               op.to_text(), auth, ctrl_cpus))
    named = {"sink": sink, "source": src, "tool": tool}  # name -> process, for the affinity report
    ready_router, ready_responder = ctx.Event(), ctx.Event()
    if apart:
        named["router"] = ctx.Process(target=_ctrl_apart, args=(layout, "router", ctrl_port, secret, None,
                                                                ready_router, stop, max_s, ctrl_cpus))
        named["responder"] = ctx.Process(target=_ctrl_apart, args=(
            layout, "responder", ctrl_port, secret, op.issue("rollout", SOURCE).to_text(), ready_responder, stop,
            max_s, ctrl_cpus))
    procs = list(named.values())
    hogs = [ctx.Process(target=_cpu_hog, args=(flood, stop, min(1.0, hog_cores / HOGS), max_s))
            for _ in range(HOGS if flood_kind == "cpu" else 0)]
    procs += hogs
    phases = (["idle"] if idle else []) + ["loaded"]
    rtts: dict[str, list[float]] = {p: [] for p in phases}
    blocks: list[dict[str, float]] = []  # p99 of each phase, block by block
    misses = dict.fromkeys(phases, 0)
    flood_msgs = flood_bytes = flood_s = flood_cpu = hog_cpu = 0.0
    try:
        for hog in hogs:
            hog.start()
            pids.append(hog.pid)
        if apart:
            named["router"].start()
            pids.append(named["router"].pid)
            _wait_event(ready_router, named["router"], "ctrl router")
        sink.start()
        pids.append(sink.pid)
        _wait_event(ready_sink, sink, "sink")
        src.start()
        pids.append(src.pid)
        _wait_event(ready_src, src, "source")
        if apart:
            named["responder"].start()
            pids.append(named["responder"].pid)
            _wait_event(ready_responder, named["responder"], "status responder")
        tool.start()
        pids.append(tool.pid)
        _collect(out, {"reachable"}, START_TIMEOUT_S + 5)
        cpus = {name: sorted(os.sched_getaffinity(p.pid)) for name, p in named.items()}
        per_block = max(1, cfg.rtt_samples // cfg.rtt_blocks)
        for _ in range(cfg.rtt_blocks):
            blocks.append({})
            for phase in phases:
                if phase == "idle":
                    flood.clear()
                    _wait_drained(received)
                else:
                    flood.set()
                    if flood_kind != "cpu":
                        _wait_for(lambda: received.value > 0, START_TIMEOUT_S, "the flood never reached the sink")
                    time.sleep(cfg.warmup_s)
                    c0, b0, t0 = received.value, received_bytes.value, time.monotonic()
                    hog0 = _proc_cpu_s([h.pid for h in hogs])
                cpu0 = _proc_cpu_s([sink.pid, src.pid])
                cmds.put((phase, per_block))
                got = _collect(out, {phase}, cfg.phase_timeout_s + 5)[phase][1]
                rtts[phase] += got[0]
                if got[0]:
                    blocks[-1][phase] = percentile(sorted(got[0]), 99)
                misses[phase] += got[1]
                if phase == "loaded":
                    flood_cpu += _proc_cpu_s([sink.pid, src.pid]) - cpu0  # (taken after the warm-up)
                    hog_cpu += _proc_cpu_s([h.pid for h in hogs]) - hog0
                    flood_msgs += received.value - c0
                    flood_bytes += received_bytes.value - b0
                    flood_s += time.monotonic() - t0
        result = {p: _summary(rtts[p], misses[p], f"{layout.name}, {p}") for p in phases}
        result["loaded"]["flood_msgs_per_s"] = flood_msgs / flood_s
        result["loaded"]["flood_bytes_per_s"] = flood_bytes / flood_s
        result["loaded"]["flood"] = flood_kind
        result["loaded"]["auth"] = auth
        result["loaded"]["flood_cpu_cores"] = flood_cpu / flood_s
        result["loaded"]["apart"] = apart
        result["cpus"] = cpus
        if hogs:
            result["loaded"]["hog_cores_asked"] = hog_cores
            result["loaded"]["hog_cores"] = hog_cpu / flood_s
        if idle:  # the isolation ratio of each block (its loaded p99 over its own idle p99)
            result["block_ratios"] = [b["loaded"] / b["idle"] for b in blocks if "loaded" in b and "idle" in b]
        return result
    finally:
        flood.clear()
        cmds.put(None)
        stop.set()
        _stop(procs)


def _wait_drained(received: Any, quiet_s: float = 0.3, timeout_s: float = 10.0) -> None:
    """After the flood stops: wait until the sink has received nothing for `quiet_s` (the
    queues along the data path are empty), so that idle samples are idle."""
    deadline = time.monotonic() + timeout_s
    last, since = received.value, time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.05)
        if received.value != last:
            last, since = received.value, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return
    raise RuntimeError("the data plane did not go quiet after the flood stopped")


def _wait_for(pred: Callable[[], bool], timeout_s: float, failure: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise RuntimeError(failure)
        time.sleep(0.01)


def _wait_reachable(tool: Any, key: str) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while not tool.query(key, timeout=1.0):
        if time.monotonic() > deadline:
            raise RuntimeError(f"the status queryable {key} never answered")


# --------------------------------------------------------------------------------------------
# orchestration


def _wait_event(event: Any, proc: Any, what: str) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while not event.wait(0.1):
        if not proc.is_alive():
            raise RuntimeError(f"{what} process exited with code {proc.exitcode} before it was ready")
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} process not ready after {START_TIMEOUT_S:.0f}s")


def _collect(out: Any, wanted: set[str], timeout_s: float) -> dict[str, tuple]:
    got: dict[str, tuple] = {}
    deadline = time.monotonic() + timeout_s
    while wanted - set(got):
        try:
            item = out.get(timeout=max(0.1, deadline - time.monotonic()))
        except queue.Empty:
            raise RuntimeError(f"no report from {sorted(wanted - set(got))} within {timeout_s:.0f}s") from None
        if item[0] == "error":
            raise RuntimeError(item[1])
        got[item[0]] = item
    return got


def _stop(procs: list[Any]) -> None:
    for p in procs:
        if p.pid is not None:
            p.join(timeout=5)
    for p in procs:
        if p.is_alive():
            p.terminate()
            p.join(timeout=5)
        if p.is_alive():
            p.kill()
            p.join(timeout=5)


def run_bench(cfg: BenchConfig | None = None, *, quick: bool = False, links: bool = True,
              progress: Callable[[str], None] = lambda _m: None) -> dict[str, Any]:
    """Run every measurement; returns the JSON document (see the module docstring)."""
    from dvla.fabric import keep_freed_buffers, new_secret

    cfg = cfg or (BenchConfig.quick() if quick else BenchConfig())
    ctx = mp.get_context("spawn")
    secret = bytes.fromhex(new_secret())
    started = time.monotonic()
    pids: list[int] = []  # every worker, all stopped before returning (recorded for checks)
    doc: dict[str, Any] = {"config": asdict(cfg), "quick": quick, "shared_memory": False, "cpus": os.cpu_count(),
                           # whether every worker keeps freed buffers in its heap, as roles do
                           "keep_freed_buffers": keep_freed_buffers()}
    throughput: dict[str, Any] = {}
    for label, target, n in (("64k", 64 * KIB, cfg.n_64k), ("1m", MIB, cfg.n_1m)):
        progress(f"throughput {label}: {cfg.rounds} rounds x {n} chunks of {payload_size(target)} bytes")
        entry = _measure_throughput(ctx, n, target, cfg, secret, pids)
        throughput[label] = entry
        doc[f"chunks_per_s_{label}"] = entry["chunks_per_s"]
        doc[f"mb_per_s_{label}"] = entry["bytes_per_s"] / 1e6
    progress("authentication: data plane without envelopes / tag / tag + identity, interleaved; one weight version")
    doc["auth"] = _measure_auth(ctx, cfg, secret, pids)
    doc["auth_throughput_ratio"] = doc["auth"]["data"]["identity"]["throughput_ratio"]
    doc["auth_extra_cpu_us_per_chunk"] = doc["auth"]["data"]["identity"]["extra_cpu_us_per_chunk"]
    layouts = [LOOPBACK]
    why_not = links_available() if links else "not asked for (--no-links)"
    doc["links_layout"] = "used" if why_not is None else f"skipped: {why_not}"
    doc["netns"] = []
    ctrl: dict[str, Any] = {}
    for layout in layouts + ([None] if why_not is None else []):
        links_cm = TwoLinks() if layout is None else None
        if links_cm is not None:
            doc["netns"] = [links_cm.sink_ns, links_cm.source_ns]
        with (links_cm if links_cm is not None else contextlib.nullcontext(layout)) as lay:
            progress(f"ctrl RTT ({lay.name}): separate sessions, idle and data plane flooded, alternating")
            separate = _measure_ctrl(ctx, lay, False, cfg, secret, pids, idle=True)
            progress(f"ctrl RTT ({lay.name}): one shared session, data plane flooded")
            shared = _measure_ctrl(ctx, lay, True, cfg, secret, pids, idle=False)
            tcp = plain = cpu = None
            apart: dict[str, Any] = {}
            if lay.name == "links":  # the controls: the same layout without envelopes, the same link without dvla
                progress(f"ctrl RTT ({lay.name}): separate sessions, trajectories without envelopes, idle and flooded, alternating")
                plain = _measure_ctrl(ctx, lay, False, cfg, secret, pids, idle=True, auth="none-data")
                progress(f"ctrl RTT ({lay.name}): separate sessions, idle and data link flooded by plain TCP, alternating")
                tcp = _measure_ctrl(ctx, lay, False, cfg, secret, pids, idle=True, flood_kind="tcp")
                for where in ("processes", "core") if len(os.sched_getaffinity(0)) >= 2 else ("processes",):
                    progress(f"ctrl RTT ({lay.name}): ctrl router and status responder in processes of their own"
                             + (", pinned to a CPU the flood does not use" if where == "core" else "")
                             + ", idle and flooded, alternating")
                    apart[where] = _measure_ctrl(ctx, lay, False, cfg, secret, pids, idle=True, apart=where)
                # the flood's own CPU (where the sink and source answer no queries), burned by
                # processes with no traffic
                cores = apart["processes"]["loaded"]["flood_cpu_cores"]
                progress(f"ctrl RTT ({lay.name}): separate sessions, idle and {cores:.2f} cores burned without traffic")
                cpu = _measure_ctrl(ctx, lay, False, cfg, secret, pids, idle=True, flood_kind="cpu", hog_cores=cores)
        ctrl[lay.name] = {"layout": lay.describe(), "idle": separate["idle"], "loaded": separate["loaded"],
                          "loaded_shared": shared["loaded"], "block_ratios": separate["block_ratios"]}
        if tcp is not None and plain is not None:
            ctrl[lay.name].update(idle_noauth=plain["idle"], loaded_noauth=plain["loaded"],
                                  block_ratios_noauth=plain["block_ratios"], idle_tcp=tcp["idle"], loaded_tcp=tcp["loaded"],
                                  block_ratios_tcp=tcp["block_ratios"])
        if cpu is not None:
            ctrl[lay.name].update(idle_cpu=cpu["idle"], loaded_cpu=cpu["loaded"], block_ratios_cpu=cpu["block_ratios"])
        for where, r in apart.items():
            ctrl[lay.name].update({f"idle_apart_{where}": r["idle"], f"loaded_apart_{where}": r["loaded"],
                                   f"block_ratios_apart_{where}": r["block_ratios"], f"cpus_apart_{where}": r["cpus"]})
    # Headline: the layout where the data link has a capacity of its own, when it could be built.
    head = "links" if "links" in ctrl else "loopback"
    doc["ctrl_rtt_layout"] = head
    doc["ctrl_rtt_p99_idle_ms"] = ctrl[head]["idle"]["p99_ms"]
    doc["ctrl_rtt_p99_loaded_ms"] = ctrl[head]["loaded"]["p99_ms"]
    doc["ctrl_rtt_p99_loaded_shared_ms"] = ctrl[head]["loaded_shared"]["p99_ms"]
    doc["loaded_over_idle"] = doc["ctrl_rtt_p99_loaded_ms"] / doc["ctrl_rtt_p99_idle_ms"]
    doc["loaded_over_idle_blocks"] = _spread(ctrl[head]["block_ratios"])
    doc["shared_over_separate"] = doc["ctrl_rtt_p99_loaded_shared_ms"] / doc["ctrl_rtt_p99_loaded_ms"]
    if "loaded_tcp" in ctrl[head]:
        doc["noauth_loaded_over_idle"] = ctrl[head]["loaded_noauth"]["p99_ms"] / ctrl[head]["idle_noauth"]["p99_ms"]
        doc["noauth_loaded_over_idle_blocks"] = _spread(ctrl[head]["block_ratios_noauth"])
        doc["tcp_flood_over_idle"] = ctrl[head]["loaded_tcp"]["p99_ms"] / ctrl[head]["idle_tcp"]["p99_ms"]
        doc["tcp_flood_over_idle_blocks"] = _spread(ctrl[head]["block_ratios_tcp"])
    for where in APART[1:]:
        if f"loaded_apart_{where}" in ctrl[head]:
            doc[f"apart_{where}_over_idle"] = (ctrl[head][f"loaded_apart_{where}"]["p99_ms"]
                                              / ctrl[head][f"idle_apart_{where}"]["p99_ms"])
            doc[f"apart_{where}_over_idle_blocks"] = _spread(ctrl[head][f"block_ratios_apart_{where}"])
    if "loaded_cpu" in ctrl[head]:
        doc["flood_cpu_cores"] = ctrl[head]["loaded_apart_processes"]["flood_cpu_cores"]
        doc["cpu_load_over_idle"] = ctrl[head]["loaded_cpu"]["p99_ms"] / ctrl[head]["idle_cpu"]["p99_ms"]
        doc["cpu_load_over_idle_blocks"] = _spread(ctrl[head]["block_ratios_cpu"])
    doc["actor_cpu_us_per_auth_chunk"] = doc["auth"]["data"]["identity"]["sub_cpu_us_per_chunk"]
    doc["throughput"] = throughput
    doc["ctrl_rtt"] = ctrl[head]
    doc["ctrl_rtt_layouts"] = ctrl
    doc["worker_pids"] = pids
    doc["elapsed_s"] = time.monotonic() - started
    return doc


def _spread(values: list[float]) -> dict[str, Any]:
    """Median, min and max of per-block ratios (None when there are none)."""
    if not values:
        return {"median": None, "min": None, "max": None, "values": []}
    return {"median": statistics.median(values), "min": min(values), "max": max(values), "values": values}


HEADLINE_KEYS = (
    "chunks_per_s_64k", "chunks_per_s_1m", "mb_per_s_64k", "mb_per_s_1m",
    "ctrl_rtt_p99_idle_ms", "ctrl_rtt_p99_loaded_ms",
    "ctrl_rtt_p99_loaded_shared_ms", "loaded_over_idle", "shared_over_separate",
    "auth_throughput_ratio", "auth_extra_cpu_us_per_chunk", "actor_cpu_us_per_auth_chunk",
)


def format_table(doc: dict[str, Any]) -> str:
    """A short human summary of `run_bench`'s document."""
    lines = [f"{'throughput':<11}{'payload':>9}{'chunks/s':>10}{'MB/s':>8}{'CPU us/chunk pub':>18}{'sub':>6}{'lost':>6}"]
    for label, e in doc["throughput"].items():
        lines.append(f"{label:<11}{e['payload_bytes']:>9}{e['chunks_per_s']:>10.0f}{e['bytes_per_s'] / 1e6:>8.0f}"
                     f"{e['pub_cpu_us_per_msg']:>18.0f}{e['sub_cpu_us_per_msg']:>6.0f}{e['lost']:>6}")
    lines.append("publish_traj of a TrajectoryChunk to subscribe_traj's inbox and a consumer thread")
    auth = doc["auth"]
    lines.append("")
    lines.append(f"{'authentication, ' + str(auth['chunk_bytes']) + ' B chunks':<36}{'chunks/s':>10}{'ratio':>7}"
                 f"{'CPU us/chunk pub':>18}{'sub':>6}")
    for mode, e in auth["data"].items():
        ratio = f"{e['throughput_ratio']:.2f}" if "throughput_ratio" in e else "1"
        lines.append(f"{mode:<36}{e['chunks_per_s']:>10.0f}{ratio:>7}{e['pub_cpu_us_per_chunk']:>18.0f}"
                     f"{e['sub_cpu_us_per_chunk']:>6.0f}")
    w = auth["weights"]
    lines.append(f"one {w['version_bytes'] >> 20} MiB weight version in {w['chunk_bytes'] >> 20} MiB chunks: "
                 + ", ".join(f"{m} seal {w[m]['seal_cpu_s']:.3f} s / open {w[m]['open_cpu_s']:.3f} s CPU"
                             for m in ("tag", "identity")))
    names = {"idle": "idle", "loaded": "flooded, own ctrl session", "loaded_shared": "flooded, shared session",
             "idle_noauth": "idle (flood unauthenticated)", "loaded_noauth": "flooded, unauthenticated",
             "idle_tcp": "idle (TCP control)", "loaded_tcp": "flooded by plain TCP",
             "idle_cpu": "idle (CPU control)", "loaded_cpu": "CPU burned, no traffic",
             "idle_apart_processes": "idle (ctrl apart)", "loaded_apart_processes": "flooded, ctrl apart",
             "idle_apart_core": "idle (ctrl on a core)", "loaded_apart_core": "flooded, ctrl on a core"}
    for layout, entry in doc["ctrl_rtt_layouts"].items():
        lines.append("")
        lines.append(f"{'ctrl RTT, ' + layout:<28}{'p50 ms':>8}{'p99 ms':>8}{'flood MB/s':>12}")
        for key, title in names.items():
            if key not in entry:
                continue
            r = entry[key]
            flood = f"{r['flood_bytes_per_s'] / 1e6:.0f}" if "flood_bytes_per_s" in r else "-"
            lines.append(f"{title:<28}{r['p50_ms']:>8.2f}{r['p99_ms']:>8.2f}{flood:>12}")
    blocks = doc["loaded_over_idle_blocks"]
    spread = f" (blocks {blocks['min']:.2f}-{blocks['max']:.2f})" if blocks["values"] else ""
    tcp = (f"\n  controls: flood without envelopes loaded/idle p99 = {doc['noauth_loaded_over_idle']:.2f}   "
           f"plain-TCP flood/idle p99 = {doc['tcp_flood_over_idle']:.2f}") if "tcp_flood_over_idle" in doc else ""
    if "cpu_load_over_idle" in doc:
        tcp += (f"   the flood's CPU ({doc['flood_cpu_cores']:.2f} cores) burned without traffic: "
                f"loaded/idle p99 = {doc['cpu_load_over_idle']:.2f}")
    for where, what in (("processes", "ctrl path in processes that carry no trajectories"),
                        ("core", "the same on a CPU of its own")):
        if f"apart_{where}_over_idle" in doc:
            tcp += f"\n  {what}: loaded/idle p99 = {doc[f'apart_{where}_over_idle']:.2f}"
    lines.append(f"headline ({doc['ctrl_rtt_layout']}): loaded/idle p99 = {doc['loaded_over_idle']:.2f}{spread}   "
                 f"shared/separate p99 = {doc['shared_over_separate']:.2f}{tcp}   links layout: {doc['links_layout']}")
    lines.append(f"actor CPU per authenticated 256 KiB chunk: {doc['actor_cpu_us_per_auth_chunk']:.0f} us "
                 f"(+{doc['auth']['data']['identity']['sub_cpu_us_per_chunk'] - doc['auth']['data']['none']['sub_cpu_us_per_chunk']:.0f} over none)")
    return "\n".join(lines)

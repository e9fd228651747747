"""Processes of the replication benchmark and of the emulated-cluster replication tests.

``python -m benchmarks.repnode --mode source|relay|sink --config ROLE.json --numel N``

Each process runs under the same :class:`~dvla.roles.runtime.RoleHost` as a real role (liveliness
token, status queryable, commands, signals, summary file), with the RoleConfig the orchestrator's
planner wrote, so it sits in the real link graph and weight tree:

- ``source`` stands where the actor does: the actor's own
  :class:`~dvla.roles.weightsync.WeightPublisher` originates the versions and serves snapshots.
  It publishes the next version each time the driver raises the number in its trigger file
  (``<run_dir>/bench/trigger``), so the driver decides when a transfer starts.
- ``relay`` is the real :class:`~dvla.roles.replicator.Replicator`, given the synthetic layout
  instead of building a policy, recording when each version's manifest and chunks reached it
  (:class:`TimedRelay`); ``--fault`` injects one fault on the way to its children (a
  corrupted chunk, or a stall in the middle of a transfer): see :class:`FaultyRelay`.
- ``sink`` stands where a rollout does: the same :class:`~dvla.roles.weightsync.WeightSync` the
  rollouts use, recording when its messages arrived, when it held each version and the
  checksum of what it holds.

No simulator, no policy: a version is a flat float32 vector of ``--numel`` elements, so the
processes start in about a second and the figures are about moving weights, nothing else.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from dvla.config import RoleConfig
from dvla.fabric import Fabric
from dvla.fabric.messages import WeightChunk, WeightManifest
from dvla.replication import HeldWeights, ParamLayout
from dvla.roles.replicator import Replicator
from dvla.roles.runtime import ExitStatus, RoleHost, open_fabric, setup_logging
from dvla.roles.swimlane import LaneContext, Swimlane
from dvla.roles.weightsync import WeightPublisher, WeightSync

log = logging.getLogger("dvla.repnode")

MODES = ("source", "relay", "sink")
#: largest tensor of the synthetic layout (elements); a real model is many tensors, not one
TENSOR_NUMEL = 1 << 22
#: versions whose timings a status reply carries (the newest ones)
KEEP_VERSIONS = 64

#: an injected relay fault: (kind, version, chunk index, seconds)
Fault = tuple[str, int, int, float]


def synthetic_layout(numel: int) -> ParamLayout:
    """A layout of `numel` float32 elements in tensors of at most :data:`TENSOR_NUMEL`."""
    if numel < 1:
        raise ValueError(f"numel must be >= 1, got {numel}")
    sizes = [TENSOR_NUMEL] * (numel // TENSOR_NUMEL) + ([numel % TENSOR_NUMEL] if numel % TENSOR_NUMEL else [])
    names = tuple(f"block{i}.weight" for i in range(len(sizes)))
    return ParamLayout(names=names, shapes=tuple((s,) for s in sizes), dtypes=("float32",) * len(sizes))


def trigger_path(run_dir: str | Path) -> Path:
    """The file whose integer content is the number of versions the source should have published."""
    return Path(run_dir) / "bench" / "trigger"


def write_trigger(run_dir: str | Path, versions: int) -> None:
    path = trigger_path(run_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(str(int(versions)))
    tmp.replace(path)


def _read_trigger(path: Path) -> int:
    try:
        return int(path.read_text().strip() or 0)
    except (OSError, ValueError):
        return 0


def _trim(d: dict[str, Any]) -> dict[str, Any]:
    keys = sorted(d, key=int)[-KEEP_VERSIONS:]
    return {k: d[k] for k in keys}


class Source:
    """The actor's place in the tree: the actor's WeightPublisher, publishing on trigger."""

    def __init__(self, cfg: RoleConfig, fabric: Fabric, layout: ParamLayout) -> None:
        self.cfg = cfg
        self.fabric = fabric
        self.layout = layout
        self.publisher = WeightPublisher(fabric, cfg.name, layout, cfg.replication)
        self.rng = np.random.default_rng(cfg.seed)
        self.flat = self.rng.standard_normal(layout.numel, dtype=np.float32)
        # The update between versions, drawn once: drawing it afresh costs ~8 ms of CPU per MiB
        # (as much as encoding and sending), which on an emulated cluster's shared cores would
        # slow the transfer still under way and count as the source's cost of a version.
        self.step = 1e-3 * self.rng.standard_normal(layout.numel, dtype=np.float32)
        self.policy_version = 0
        self.env_steps = 0
        self.published: dict[str, dict[str, Any]] = {}

    def build(self, sl: Swimlane) -> None:
        self.publisher.serve()  # catch-up for children
        sl.lane("publish", self._publish)

    def _publish(self, ctx: LaneContext) -> None:
        trigger = trigger_path(self.cfg.run_dir)
        while ctx.running:
            if self.policy_version >= _read_trigger(trigger):
                ctx.sleep(0.005)
                continue
            with ctx.busy():
                t0 = time.time_ns()
                enc = self.publisher.encode(self.flat)
                t_enc = time.time_ns()
                # Recorded before sending: a replica may hold the version before the last put returns.
                m = enc.manifest
                entry = {"t0_ns": t0, "encoded_ns": t_enc, "payload_bytes": m.total_bytes,
                         "encoding": m.encoding, "checksum": m.checksum}
                self.published = _trim({**self.published, str(m.version): entry})
                sent = self.publisher.send(enc)
                t1 = time.time_ns()
                self.policy_version = m.version
                self.published[str(m.version)] = {**entry, "sent_ns": t1, "bytes": sent}
                log.info("published v%d (%s, %d bytes) in %.3f s", m.version, m.encoding, sent, (t1 - t0) / 1e9)
                # The next version's parameters: every element moves (one vector add).
                self.flat += self.step
            ctx.count()

    def status_extra(self) -> dict[str, Any]:
        return {"published": self.published}

    def close(self) -> None:
        pass


class Arrivals:
    """When the manifest and the first and last chunk of each version reached a receiving lane
    (a sink's: the delivery time split into waiting for the data and processing it; a relay's:
    with its children's, how long it held the stream up)."""

    def __init__(self) -> None:
        self.seen: dict[int, dict[str, int]] = {}

    def __call__(self, msg: Any, _envelope: bytes) -> None:
        now = time.time_ns()
        if isinstance(msg, WeightManifest):
            self.seen[msg.version] = {"manifest_ns": now}
        elif isinstance(msg, WeightChunk):
            seen = self.seen.setdefault(msg.version, {})
            seen.setdefault("first_chunk_ns", now)
            seen["last_chunk_ns"] = now
        while len(self.seen) > KEEP_VERSIONS:
            self.seen.pop(min(self.seen))

    def status(self) -> dict[str, dict[str, int]]:
        return {str(v): dict(t) for v, t in list(self.seen.items())}


class Sink:
    """A rollout's place in the tree: follows its parent, records what it holds and when."""

    def __init__(self, cfg: RoleConfig, fabric: Fabric, layout: ParamLayout) -> None:
        self.cfg = cfg
        self.fabric = fabric
        self.layout = layout
        self.policy_version = -1
        self.env_steps = 0
        self.held: dict[str, dict[str, Any]] = {}
        self.arrivals = Arrivals()

    def build(self, sl: Swimlane) -> None:
        self.weights = WeightSync(self.fabric, HeldWeights(self.layout), (self.cfg.parent, *self.cfg.ancestors[1:]),
                                  self._on_version, on_message=self.arrivals)
        sl.lane("sync", self._sync)

    def _on_version(self, version: int) -> None:
        # Held from here on: verified against the manifest's checksum and swapped in.
        self.held[str(version)] = {"held_ns": time.time_ns(), "checksum": self.weights.held.checksum,
                                   "parent": self.weights.parent, **self.arrivals.seen.get(version, {})}
        self.held = _trim(self.held)
        self.policy_version = version

    def _sync(self, ctx: LaneContext) -> None:
        while ctx.running:
            self.weights.step(ctx)

    def status_extra(self) -> dict[str, Any]:
        return {"held": self.held, "weights": self.weights.status()}

    def close(self) -> None:
        pass


class TimedRelay(Replicator):
    """The replicator, recording when each version's messages reached it (its status's
    ``arrivals``): with its children's arrival times, how long it held the stream up."""

    def build(self, sl: Swimlane) -> None:
        super().build(sl)
        self.arrivals = Arrivals()
        cut_through = self.weights.on_message

        def on_message(msg: Any, envelope: bytes) -> None:
            self.arrivals(msg, envelope)
            cut_through(msg, envelope)

        self.weights.on_message = on_message

    def status_extra(self) -> dict[str, Any]:
        return {**super().status_extra(), "arrivals": self.arrivals.status()}


class FaultyRelay(TimedRelay):
    """A replicator with injected faults on the way to its children (tests, chaos):

    - ``corrupt:V:I`` flips a byte of chunk I of version V (signed afresh, so only the checksum
      can catch it; its own verified copy stays correct, so its snapshot repairs the children);
    - ``stall:V:I:S`` stops forwarding for S seconds after chunk I of version V (a transfer
      caught in the middle, e.g. to kill the relay at a known point).
    """

    def __init__(self, cfg: RoleConfig, fabric: Fabric, layout: ParamLayout, faults: list[Fault]) -> None:
        super().__init__(cfg, fabric, layout)
        self.faults = {(v, i): (kind, seconds) for kind, v, i, seconds in faults}
        self.injected = 0

    def build(self, sl: Swimlane) -> None:
        super().build(sl)
        self.stopping = sl.stop_event
        # Between receiving and forwarding: the faults go in front of the replicator's own
        # cut-through, which its WeightSync calls for every verified message.
        self.cut_through = self.weights.on_message
        self.weights.on_message = self._inject

    def _inject(self, msg: Any, envelope: bytes) -> None:
        fault = self.faults.get((msg.version, msg.index)) if isinstance(msg, WeightChunk) else None
        if fault is None:
            self.cut_through(msg, envelope)
            return
        (kind, seconds), version, index = fault, msg.version, msg.index
        if kind == "corrupt":
            data = bytearray(msg.data)
            data[len(data) // 2] ^= 0xFF
            msg = dataclasses.replace(msg, data=bytes(data))
            envelope = self.fabric.seal(self.fabric.keys.weights_signed(), msg)  # validly signed, wrong bytes
            self.injected += 1
            log.warning("fault injection: flipped a byte of chunk %d of v%d", index, version)
        self.cut_through(msg, envelope)
        if kind == "stall":
            self.injected += 1
            log.warning("fault injection: forwarding stalls %.1f s after chunk %d of v%d", seconds, index, version)
            # Let the forward lane send what came before, then hold the receive lane.
            deadline = time.monotonic() + 5.0
            while self.outbox.depth and time.monotonic() < deadline:
                time.sleep(0.005)
            self.stopping.wait(seconds)

    def status_extra(self) -> dict[str, Any]:
        return {**super().status_extra(), "faults_injected": self.injected}


def make_node(mode: str, cfg: RoleConfig, fabric: Fabric, layout: ParamLayout, faults: list[Fault]) -> Any:
    if mode == "source":
        return Source(cfg, fabric, layout)
    if mode == "sink":
        return Sink(cfg, fabric, layout)
    if faults:
        return FaultyRelay(cfg, fabric, layout, faults)
    return TimedRelay(cfg, fabric, layout)


def parse_fault(text: str) -> Fault:
    """``corrupt:V:I`` or ``stall:V:I:S`` -> (kind, version, chunk index, seconds)."""
    parts = text.split(":")
    try:
        if parts[0] == "corrupt" and len(parts) == 3:
            return "corrupt", int(parts[1]), int(parts[2]), 0.0
        if parts[0] == "stall" and len(parts) == 4:
            return "stall", int(parts[1]), int(parts[2]), float(parts[3])
    except ValueError:
        pass
    raise SystemExit(f"--fault: expected corrupt:VERSION:CHUNK or stall:VERSION:CHUNK:SECONDS, got {text!r}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="a source, relay or sink of the replication benchmark")
    p.add_argument("--mode", choices=MODES, required=True)
    p.add_argument("--config", required=True, help="RoleConfig JSON written by the planner")
    p.add_argument("--numel", type=int, required=True, help="float32 elements per version")
    p.add_argument("--fault", action="append", default=[], help="relay only, repeatable: corrupt:V:I or stall:V:I:S (see FaultyRelay)")
    args = p.parse_args(argv)
    cfg = RoleConfig.from_json(Path(args.config).read_text())
    setup_logging(cfg.name)
    layout = synthetic_layout(args.numel)
    fabric = open_fabric(cfg)
    try:
        node = make_node(args.mode, cfg, fabric, layout, [parse_fault(f) for f in args.fault])
        host = RoleHost(cfg, fabric, node)
        signal.signal(signal.SIGTERM, lambda *_: host.swimlane.stop())
        signal.signal(signal.SIGINT, lambda *_: host.swimlane.stop())
        return int(host.run())
    except Exception:
        log.exception("%s failed", cfg.name)
        return int(ExitStatus.ERROR)
    finally:
        fabric.close()


if __name__ == "__main__":
    sys.exit(main())

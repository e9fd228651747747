"""The learner group: the actors of a run as data-parallel ranks over ``torch.distributed``.

Gradients are averaged by ``DistributedDataParallel``; whatever else must agree is summed with
:meth:`LearnerGroup.sum` / :func:`all_reduce_sum` (docs/learners.md lists what), so every rank
holds bit-identical parameters. Rank 0 publishes, checkpoints and hands its state to the others
at start (:meth:`LearnerGroup.sync_from_root`). A group of one opens no process group. A
collective that waits past the group's timeout raises, and the role exits so the orchestrator
restarts the whole group from its last checkpoint.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import socket
import struct
from datetime import timedelta
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor, nn

from ..config import GroupRank

log = logging.getLogger("dvla.group")

__all__ = ["LearnerGroup", "all_reduce_sum"]


def all_reduce_sum(t: Tensor) -> Tensor:
    """``t`` summed over the learner group in place (unchanged outside a group of several)."""
    if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        dist.all_reduce(t)
    return t


class _Evaluate(nn.Module):
    """``policy.evaluate`` as a module's ``forward``: DDP synchronises gradients of what runs
    through ``forward`` only, and the learner's training forward is ``evaluate``."""

    def __init__(self, policy: nn.Module) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, obs: Any, actions: Tensor, extras: Any = None) -> tuple[Tensor, Tensor, Tensor]:
        return self.policy.evaluate(obs, actions, extras) if extras else self.policy.evaluate(obs, actions)


class LearnerGroup:
    """This process's rank in the learner group (``spec`` None: a group of one)."""

    def __init__(self, spec: GroupRank | None, device: torch.device, address: str | None = None) -> None:
        self.spec = spec
        self.device = device
        self.rank = spec.rank if spec else 0
        self.world_size = spec.world_size if spec else 1
        self.backend = "none"
        if self.world_size > 1:
            assert spec is not None
            self.backend = spec.backend if spec.backend != "auto" else ("nccl" if device.type == "cuda" else "gloo")
            if self.backend == "gloo" and address and "GLOO_SOCKET_IFNAME" not in os.environ:
                iface = interface_of(address)
                if iface:  # gloo's own choice (the host name's address) may not exist in a netns
                    os.environ["GLOO_SOCKET_IFNAME"] = iface
            log.info("rank %d/%d: rendezvous %s (%s)", self.rank, self.world_size, spec.init_method, self.backend)
            dist.init_process_group(self.backend, init_method=spec.init_method, rank=self.rank,
                                    world_size=self.world_size, timeout=timedelta(seconds=spec.timeout_s))

    @property
    def is_root(self) -> bool:
        return self.rank == 0

    def train_module(self, policy: nn.Module) -> Any:
        """What the learner calls for its training forward: ``policy.evaluate``, gradient-averaged
        across ranks by DDP in a group of several."""
        if self.world_size == 1:
            return policy.evaluate
        from torch.nn.parallel import DistributedDataParallel

        ids = [self.device.index or 0] if self.device.type == "cuda" else None
        # Buffers (e.g. observation statistics) are agreed by the policy itself (all_reduce_sum).
        return DistributedDataParallel(_Evaluate(policy), device_ids=ids, forward_sync_buffers=False)

    def sum(self, values: list[float]) -> list[float]:
        """``values`` summed element-wise across ranks (float64; one collective)."""
        if self.world_size == 1:
            return [float(v) for v in values]
        t = torch.tensor(values, dtype=torch.float64, device=self._comm_device())
        dist.all_reduce(t)
        return t.tolist()

    def sync_from_root(self, policy: nn.Module, optimizer: torch.optim.Optimizer, counters: list[int]) -> list[int]:
        """Give every rank rank 0's weights, buffers, optimizer state and ``counters``; returns
        rank 0's counters. Tensors only travel (names and shapes as JSON), never pickles."""
        if self.world_size == 1:
            return counters
        from .optstate import optimizer_from_tensors, optimizer_to_tensors

        with torch.no_grad():
            for t in policy.state_dict().values():
                dist.broadcast(t, 0)
        opt = optimizer_to_tensors(optimizer.state_dict()) if self.is_root else None
        tensors, meta = self._broadcast_tensors(opt)
        if not self.is_root:
            optimizer.load_state_dict(optimizer_from_tensors(tensors, meta, optimizer.state_dict()))
        c = torch.tensor(counters, dtype=torch.int64, device=self._comm_device())
        dist.broadcast(c, 0)
        return [int(x) for x in c.tolist()]

    def _broadcast_tensors(self, payload: tuple[dict[str, Tensor], str] | None) -> tuple[dict[str, Tensor], str]:
        dev = self._comm_device()
        if self.is_root:
            assert payload is not None
            tensors, meta = payload
            head = json.dumps({"meta": meta, "tensors": [[k, str(v.dtype).removeprefix("torch."), list(v.shape)]
                                                         for k, v in tensors.items()]}).encode()
        else:
            head = b""
        n = torch.tensor([len(head)], dtype=torch.int64, device=dev)
        dist.broadcast(n, 0)
        buf = torch.frombuffer(bytearray(head), dtype=torch.uint8).to(dev) if self.is_root else torch.empty(int(n), dtype=torch.uint8, device=dev)
        dist.broadcast(buf, 0)
        doc = json.loads(buf.cpu().numpy().tobytes())
        out: dict[str, Tensor] = {}
        for name, dtype, shape in doc["tensors"]:
            t = tensors[name].to(dev).contiguous() if self.is_root else torch.empty(shape, dtype=getattr(torch, dtype), device=dev)
            dist.broadcast(t, 0)
            out[name] = t
        return out, doc["meta"]

    def _comm_device(self) -> torch.device:
        return self.device if self.backend == "nccl" else torch.device("cpu")

    def close(self) -> None:
        if self.world_size > 1 and dist.is_initialized():
            try:
                dist.destroy_process_group()
            except Exception as err:  # a peer already gone: nothing left to tear down cleanly
                log.info("process group teardown: %s", err)


def interface_of(address: str) -> str | None:
    """Name of the network interface holding IPv4 ``address`` (None if none does)."""
    try:
        want = socket.inet_aton(socket.gethostbyname(address))
    except OSError:
        return None
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _index, name in socket.if_nameindex():
            try:
                req = struct.pack("256s", name.encode()[:15])
                got = fcntl.ioctl(s.fileno(), 0x8915, req)[20:24]  # SIOCGIFADDR
            except OSError:
                continue
            if got == want:
                return name
    return None


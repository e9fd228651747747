"""Weight replication: from the actor's state_dict to bit-identical replicas on every rollout.

The package is pure logic (no networking, no threads of its own); the roles wire it to the
fabric (dvla/roles/weightsync.py).

* :mod:`dvla.replication.layout` maps a torch state_dict to one flat float32 vector
  (:class:`ParamLayout`, :func:`flatten`, :func:`unflatten_into`).
* :mod:`dvla.replication.encoding` encodes successive vectors as versions (``full``,
  ``delta-bf16``, ``delta-topk``) with error feedback (:class:`WeightEncoder`), reassembles
  payloads from chunks (:class:`ChunkAssembler`) and holds the newest verified version
  (:class:`HeldWeights`).

The flow from the actor's update to a rollout's installed weights: docs/replication.md and
docs/architecture.md.
"""

from dvla.replication.encoding import (
    ChecksumMismatch, ChunkAssembler, CorruptPayload, HeldWeights, NeedSnapshot, StaleVersion, WeightEncoder, WeightVersion,
    bf16_round_bits, bf16_to_float32, checksum, chunk_count, split_chunks, split_encoding,
)
from dvla.replication.layout import (
    LayoutMismatch, ParamLayout, ReplicationError, bind_flat, flatten, replicated_tensors, unflatten_into,
)

__all__ = [
    "ChecksumMismatch", "ChunkAssembler", "CorruptPayload", "HeldWeights", "LayoutMismatch", "NeedSnapshot",
    "ParamLayout", "ReplicationError", "StaleVersion", "WeightEncoder", "WeightVersion", "bf16_round_bits",
    "bf16_to_float32", "bind_flat", "checksum", "chunk_count", "flatten", "replicated_tensors", "split_chunks",
    "split_encoding", "unflatten_into",
]

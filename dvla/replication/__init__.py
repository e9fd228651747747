"""Weight replication: from the actor's state_dict to bit-identical replicas on every rollout.

The package is pure logic (no networking, no threads of its own); the roles wire it to the
fabric (dvla/roles/weightsync.py).

* :mod:`dvla.replication.layout` maps a torch state_dict to one flat float32 vector
  (:class:`ParamLayout`, :func:`flatten`, :func:`unflatten_into`).
* :mod:`dvla.replication.encoding` encodes successive vectors as versions (``full``,
  ``delta-bf16``, ``delta-topk``) with error feedback (:class:`WeightEncoder`), reassembles
  payloads from chunks (:class:`ChunkAssembler`) and holds the newest verified version
  (:class:`HeldWeights`).

Flow: the actor calls ``WeightEncoder.encode(flatten(model, layout, buf))`` once per policy
version and sends the signed manifest, then the chunks. Each relay forwards every verified
message to its children as it arrives, and feeds the chunks to a ``ChunkAssembler`` whose
payload its ``HeldWeights.apply`` decodes and verifies; each rollout does the same, and its
infer lane copies ``held.active`` into the policy between two batches. A snapshot (catch-up) is
the held version sent whole, through the same assembler and ``apply``. See docs/replication.md.
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

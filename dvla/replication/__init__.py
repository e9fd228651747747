"""Weight replication: from the actor's state_dict to bit-identical replicas on every rollout.

The package is pure logic (no networking, no threads); the roles wire it to the fabric.

* :mod:`dvla.replication.layout` maps a torch state_dict to one flat float32 vector
  (:class:`ParamLayout`, :func:`flatten`, :func:`unflatten_into`).
* :mod:`dvla.replication.encoding` encodes successive vectors as versions (``full``,
  ``delta-bf16``, ``delta-topk``) with error feedback, splits payloads into chunks, reassembles
  them (:class:`ChunkAssembler`) and decodes them with checksum verification and a dual-pool
  swap (:class:`WeightDecoder`).

Typical flow: the actor calls ``WeightEncoder.encode(flatten(model, layout, buf))`` once per
policy version and sends the manifest plus chunks; each relay feeds chunks to a
``ChunkAssembler`` (forwarding each new one to its children) and applies the assembled payload
to its own ``WeightDecoder``; each rollout does the same, then ``swap()`` and
``unflatten_into(decoder.active, policy, layout)`` between steps. See docs/replication.md.
"""

from dvla.replication.encoding import (
    MANIFEST_FIELDS,
    ChecksumMismatch,
    ChunkAssembler,
    CorruptPayload,
    EncodedVersion,
    Manifest,
    NeedSnapshot,
    Snapshot,
    StaleVersion,
    WeightDecoder,
    WeightEncoder,
    bf16_round_bits,
    bf16_to_float32,
    checksum,
    chunk_count,
    split_chunks,
    split_encoding,
)
from dvla.replication.layout import (
    LayoutMismatch, ParamLayout, ReplicationError, bind_flat, flatten, replicated_tensors, unflatten_into,
)

__all__ = [
    "MANIFEST_FIELDS",
    "ChecksumMismatch",
    "ChunkAssembler",
    "CorruptPayload",
    "EncodedVersion",
    "LayoutMismatch",
    "Manifest",
    "NeedSnapshot",
    "ParamLayout",
    "ReplicationError",
    "Snapshot",
    "StaleVersion",
    "WeightDecoder",
    "WeightEncoder",
    "bf16_round_bits",
    "bf16_to_float32",
    "bind_flat",
    "replicated_tensors",
    "checksum",
    "chunk_count",
    "flatten",
    "split_chunks",
    "split_encoding",
    "unflatten_into",
]

"""dvla's transport: two Zenoh sessions per process (data and ctrl), one codec, signed control
traffic, accounting and liveliness. Embeddable: nothing here knows dvla's roles or topologies.

    from dvla.fabric import Fabric, plane_config, load_secret
    fabric = Fabric(run="myrun", name="my-sampler",
                    data_conf=plane_config(connect=["tcp/10.0.0.1:17401"]),
                    ctrl_conf=plane_config(mode="client", connect=["tcp/10.0.0.1:17400"]),
                    secret=load_secret(None))          # DVLA_SECRET
    fabric.publish_traj(chunk)

See docs/embedding.md and docs/wire-format.md.
"""

from .accounting import Accounting
from .codec import Limits, decode, encode
from .errors import CodecError, FabricError, SecretError, SignatureError
from .fabric import CTRL, DATA, Fabric, Inbox
from .heap import keep_freed_buffers
from .keys import KeySpace
from .messages import (
    Command,
    EvalResult,
    LedgerRecord,
    Receipt,
    ReceiptRequest,
    RoleStatus,
    SnapshotRequest,
    TrajectoryChunk,
    WeightChunk,
    WeightManifest,
)
from .signing import Signer, Verifier, load_secret, new_secret
from .zconfig import TlsFiles, plane_config

__all__ = [
    "Accounting", "CTRL", "CodecError", "Command", "DATA", "EvalResult", "Fabric", "FabricError", "Inbox",
    "KeySpace", "LedgerRecord", "Limits", "Receipt", "ReceiptRequest", "RoleStatus", "SecretError",
    "SignatureError", "Signer", "SnapshotRequest", "TlsFiles", "TrajectoryChunk", "Verifier", "WeightChunk",
    "WeightManifest", "decode", "encode", "keep_freed_buffers", "load_secret", "new_secret", "plane_config",
]

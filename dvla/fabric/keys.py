"""Every Zenoh key expression dvla uses, built in one place.

Roles and tools never format keys themselves: they ask a :class:`KeySpace`. The data plane
(``data/``) and the control plane (``ctrl/``) are disjoint subtrees so that each plane's session
only ever declares keys of its own subtree.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")

def check_name(kind: str, value: str) -> str:
    """A run id or role name must be one key chunk: no '/', '*', '$', '?', '#'."""
    if not isinstance(value, str) or not _NAME.match(value):
        raise ValueError(f"{kind} {value!r} is not a valid key chunk (letters, digits, '_', '.', '-'; max 64)")
    return value


@dataclass(frozen=True)
class KeySpace:
    """Key expressions of one run: ``dvla/<run>/<plane>/<kind>/<name>``."""

    run: str

    def __post_init__(self) -> None:
        check_name("run id", self.run)

    @property
    def root(self) -> str:
        return f"dvla/{self.run}"

    # -- data plane: trajectories, high rate, bulky ------------------------------------------
    def traj(self, rollout: str) -> str:
        """TrajectoryChunk stream of one rollout (rollout -> actor)."""
        return f"{self.root}/data/traj/{check_name('rollout', rollout)}"

    def traj_all(self) -> str:
        return f"{self.root}/data/traj/*"

    # -- control plane: weights, commands, status; low rate, urgent --------------------------
    def weights(self, sender: str) -> str:
        """Weight manifests and chunks sent by `sender` to its children."""
        return f"{self.root}/ctrl/weights/{check_name('sender', sender)}"

    def weights_signed(self) -> str:
        """The key expression every weight manifest and chunk is *signed* for, whichever
        `weights(sender)` key carries it: replicators forward the actor's envelopes unchanged.
        Nothing is published on it."""
        return f"{self.root}/ctrl/weights"

    def snapshot(self, sender: str) -> str:
        """Queryable serving `sender`'s latest full weights (catch-up)."""
        return f"{self.root}/ctrl/snapshot/{check_name('sender', sender)}"

    def cmd(self, target: str) -> str:
        """Commands for one role, or for every role with target ``all``."""
        return f"{self.root}/ctrl/cmd/{check_name('target', target)}"

    def status(self, role: str) -> str:
        """Queryable answering with the role's RoleStatus."""
        return f"{self.root}/ctrl/status/{check_name('role', role)}"

    def status_all(self) -> str:
        return f"{self.root}/ctrl/status/*"

    def alive(self, role: str) -> str:
        """Liveliness token held while the role's process is up."""
        return f"{self.root}/ctrl/alive/{check_name('role', role)}"

    def alive_all(self) -> str:
        return f"{self.root}/ctrl/alive/*"

    def eval(self, role: str) -> str:
        """EvalResult stream of an evaluator."""
        return f"{self.root}/ctrl/eval/{check_name('role', role)}"

    def eval_all(self) -> str:
        return f"{self.root}/ctrl/eval/*"

    def ledger(self, rollout: str) -> str:
        """LedgerRecord stream of a rollout whose counter file is elsewhere (rollout -> learner)."""
        return f"{self.root}/ctrl/ledger/{check_name('rollout', rollout)}"

    def ledger_all(self) -> str:
        return f"{self.root}/ctrl/ledger/*"

    def receipt(self, learner: str) -> str:
        """Queryable of a learner: how far it got a rollout's chunks (a stopping rollout asks)."""
        return f"{self.root}/ctrl/receipt/{check_name('learner', learner)}"

    @staticmethod
    def last(key: str) -> str:
        """The final chunk of a key (the role or sender name)."""
        return str(key).rsplit("/", 1)[-1]

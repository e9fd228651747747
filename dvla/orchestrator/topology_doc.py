"""docs/topology.md, generated from the schema in dvla/config.py: its fields, defaults, ranges
and `#:` field comments.

    python -m dvla.orchestrator.topology_doc > docs/topology.md

A unit test compares the file with :func:`render`, so the page cannot drift from the schema.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
import sys
import typing
from typing import Any

from .. import config
from ..config import MAX_SHOWN
from .topology import LOADER_OWNED, MAX_DEPTH, MAX_FILE_BYTES

HEADER = """# Topology files

A topology YAML describes one run. `dvla plan FILE` validates it and shows the placement; every
problem is reported at once as `file:line: key.path: message`, and unknown keys are rejected.
The schema is `dvla/config.py` (this page is generated from its field comments by
`python -m dvla.orchestrator.topology_doc`).

```yaml
run: local
task: {env: PushCube-v1, budget: {until_success: 0.8}}
racks:
  - name: rack0
    nodes:
      - name: node0
        roles: [{role: actor}, {role: replicator}, {role: rollout, count: 2}, {role: evaluator}]
```
"""

FOOTER = """Roles: `actor` (exactly one publishes weights: the first), `rollout`, `replicator` (at most one per node; the first of a rack relays for the rack), `evaluator`.
"""

#: what the loader refuses whatever the schema says (a topology file is input like any other)
LIMITS = (f"\nA topology file is input like any other, checked before anything starts: at most {MAX_FILE_BYTES} bytes, "
          f"nested at most {MAX_DEPTH} levels, without YAML anchors, aliases or merge keys (`&`, `*`, `<<`); `.nan` and "
          "`.inf` are refused in every number; rack and node "
          "names are one Zenoh key chunk (1 to 64 of letters, digits, `_`, `.`, `-`, starting with a letter or digit, "
          "and so are the process names `<role>-<node>-<index>` made from them); `host` and `address` are a DNS name "
          "or an IP address (IPv6 bare or in brackets; nothing starting with `-`; the login user goes in `ssh.user`); "
          "a `module:Class` policy must import on the machine running `dvla plan`/`dvla up` (with the working "
          f"directory on the path, as the roles import it). Values quoted in messages are cut to {MAX_SHOWN} "
          "characters.\n")


def field_comments(cls: type) -> dict[str, str]:
    """name -> the `#:` comment lines right above the field's declaration, joined."""
    out: dict[str, str] = {}
    pending: list[str] = []
    for line in inspect.getsource(cls).splitlines():
        stripped = line.strip()
        if stripped.startswith("#:"):
            pending.append(stripped[2:].strip())
            continue
        m = re.match(r"^([A-Za-z_]\w*)\s*:", stripped)
        if m and pending:
            out[m.group(1)] = " ".join(pending)
        pending = []
    return out


def _nested(hint: Any) -> tuple[type | None, str]:
    """(dataclass type inside the hint, path suffix): X -> (X, ""), tuple[X, ...] -> (X, "[]"),
    X | None -> (X, "")."""
    hint = config.unwrap_optional(hint)[0]
    if dataclasses.is_dataclass(hint):
        return hint, ""
    item = typing.get_args(hint)[0] if typing.get_origin(hint) is tuple else None
    return (item, "[]") if dataclasses.is_dataclass(item) else (None, "")


def _default(f: dataclasses.Field, nested: type | None) -> str:
    if f.default is not dataclasses.MISSING:
        return f"`{f.default!r}`"
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return "`(see below)`" if nested is not None else f"`{f.default_factory()!r}`"  # type: ignore[misc]
    return "`required`"


def _sections(cls: type, path: str) -> list[str]:
    hints = typing.get_type_hints(cls)
    comments = field_comments(cls)
    rows, below = [], []
    for f in dataclasses.fields(cls):
        if cls is config.Topology and f.name in LOADER_OWNED:
            continue
        nested, suffix = _nested(hints[f.name])
        meaning = comments.get(f.name, "")
        allowed = f.metadata.get("range")
        rows.append(f"| `{f.name}` | {_default(f, nested)} | {f'`{allowed.describe(f.name)}`' if allowed else ''} | {meaning} |")
        if nested is not None:
            sub = f"{path}.{f.name}{suffix}" if path else f"{f.name}{suffix}"
            below.extend(_sections(nested, sub))
    title = path or "top level"
    table = [f"## `{title}`", "", "| key | default | range | meaning |", "|---|---|---|---|", *rows, ""]
    return table + below


def render() -> str:
    """The whole page."""
    lanes = "; ".join(f"`{role}`: " + ", ".join(f"`{lane}`" for lane in names) for role, names in config.ROLE_LANES.items())
    pinning = (f"\nLanes `lane_cpus` can pin (each is one thread of the role's process): {lanes}. A pinned lane's thread "
               "moves to its cores as it starts; the process's other threads (its other lanes, Zenoh's I/O threads) stay "
               "on the role's `cpus`. Example: every role on core 1 but the simulators, alone on core 0 "
               "(what `dvla bench swimlane --placement split` runs):\n\n"
               "```yaml\n      - name: node0\n        cpus: [1]\n        roles:\n          - role: actor\n"
               "          - role: replicator\n          - {role: rollout, count: 2, lane_cpus: {sim: [0]}}\n```\n")
    return HEADER + "\n" + "\n".join(_sections(config.Topology, "")) + "\n" + FOOTER + pinning + LIMITS


if __name__ == "__main__":
    sys.stdout.write(render())

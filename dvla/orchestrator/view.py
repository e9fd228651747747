"""Rendering of collected status: a table for people, JSON for programs. Collection happens
elsewhere (monitor.py, status command); nothing here talks to the network."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from ..fabric.messages import RoleStatus


def policy_lag(s: RoleStatus, latest: int | None = None) -> int | None:
    """Versions a rollout (or evaluator) is behind the newest published one; None for others."""
    if s.kind not in ("rollout", "evaluator") or latest is None:
        return None
    return max(0, latest - s.policy_version)


def lag_cell(s: RoleStatus, latest: int) -> str:
    """LAG column: a leaf's versions behind; for the actor, the mean lag of the chunks it learned from."""
    if s.kind == "actor":
        mean = s.extra.get("policy_lag_mean")
        return "-" if mean is None else f"~{float(mean):.1f}"
    lag = policy_lag(s, latest)
    return "-" if lag is None else str(lag)


def lane_utilisation(s: RoleStatus) -> dict[str, float]:
    """Busy fraction of each lane over the role's recent window."""
    return {lane: float(st.get("utilisation", 0.0)) for lane, st in s.lanes.items()}


#: version of the JSON document `dvla status --format json` prints (docs/status.md)
STATUS_SCHEMA = "dvla.status/2"


def plane_totals(statuses: dict[str, RoleStatus]) -> dict[str, dict[str, int]]:
    """Every role's plane counters summed: {plane: {counter: n}} (per-peer tables left out)."""
    out: dict[str, dict[str, int]] = {}
    for s in statuses.values():
        for plane, counters in s.planes.items():
            tot = out.setdefault(plane, {})
            for name, n in counters.items():
                if name != "peers" and isinstance(n, (int, float)):
                    tot[name] = tot.get(name, 0) + int(n)
    return out


def render_json(statuses: dict[str, RoleStatus], extra: dict[str, Any] | None = None) -> str:
    """The document of docs/status.md: every role's status plus the run's plane totals."""
    latest = latest_version(statuses)
    roles = []
    for name in sorted(statuses):
        d = dataclasses.asdict(statuses[name])
        d["policy_lag"] = policy_lag(statuses[name], latest)
        d["lane_utilisation"] = lane_utilisation(statuses[name])
        roles.append(d)
    doc = {"schema": STATUS_SCHEMA, "roles": roles, "planes": plane_totals(statuses), "latest_version": latest,
           **(extra or {})}
    return json.dumps(doc, indent=1, sort_keys=True, default=str)


def latest_version(statuses: dict[str, RoleStatus]) -> int:
    return max((int(s.extra.get("published_version", s.policy_version)) for s in statuses.values() if s.kind == "actor"), default=0)


def _lanes(s: RoleStatus) -> str:
    """``sim@0 98% infer 11% ...``: a lane pinned apart from its process (``lane_cpus``) shows its cores."""
    placement = s.extra.get("placement") or {}
    own = placement.get("cpus")
    pinned = placement.get("lanes") or {}
    cells = []
    for lane, util in lane_utilisation(s).items():
        cores = pinned.get(lane)
        at = "@" + ",".join(str(c) for c in cores) if cores and cores != own else ""
        cells.append(f"{lane}{at} {100 * util:.0f}%")
    workers = s.extra.get("sim_workers") or []
    if workers:  # a rollout's simulator worker processes: each one's busy share ("dead" once it is gone)
        shares = [f"{100 * float(w.get('busy', 0.0)):.0f}%" if w.get("alive", True) else "dead" for w in workers]
        cells.append(f"| workers {'/'.join(shares)}")
    return " ".join(cells)


def _infer_cell(s: RoleStatus) -> str:
    """Rollouts' per-step policy inference latency percentiles ("-" for other roles)."""
    if "infer_ms_p50" not in s.extra:
        return "-"
    return f"{float(s.extra['infer_ms_p50']):.1f}/{float(s.extra.get('infer_ms_p99', 0.0)):.1f}"


def render_table(
    statuses: dict[str, RoleStatus], expected: list[str] | None = None, restarts: dict[str, int] | None = None
) -> str:
    latest = latest_version(statuses)
    restarts = restarts or {}
    header = ["ROLE", "NODE", "RACK", "STATE", "VERSION", "LAG", "STEPS", "STEPS/S", "INFER ms p50/p99", "RESTARTS", "LANES (busy)"]
    rows = []
    names = sorted(set(statuses) | set(expected or []))
    for name in names:
        s = statuses.get(name)
        if s is None:
            rows.append([name, "-", "-", "silent", "-", "-", "-", "-", "-", str(restarts.get(name, 0)), ""])
            continue
        version = s.extra.get("published_version", s.policy_version) if s.kind == "actor" else s.policy_version
        rows.append([name, s.node, s.rack, s.state, str(version), lag_cell(s, latest),
                     str(s.env_steps), f"{s.steps_per_s:.0f}", _infer_cell(s), str(restarts.get(name, 0)), _lanes(s)])
    widths = [max(len(r[i]) for r in [header] + rows) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in [header] + rows]
    return "\n".join(lines)

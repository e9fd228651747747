"""Chaos during training on the emulated 8-node cluster (benchmarks/chaos.py): rollouts, a
replicator and the actor killed with SIGKILL while one rack uplink drops 5% of its packets.

The short profile (one kill of each kind, ~3 minutes) runs in the default suite; the 5-minute
profile (a rollout every 30 s) is marked slow. Both check that learning went on after every fault,
that every live replica ends bit-identical to the actor's latest version, that versions never went
backwards, that the loss rules really dropped packets, and that the chunk accounting closes
exactly with each killed incarnation's loss inside its bound."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from benchmarks.chaos import FULL, QUICK, Profile, iptables_usable, run_chaos
from dvla.orchestrator.netns import list_links, list_netns, run_prefix

from .support import ROOT, free_port_block

_why = iptables_usable()
pytestmark = [pytest.mark.netns, pytest.mark.chaos,
              pytest.mark.skipif(_why is not None, reason=f"chaos needs root, netns and iptables: {_why}")]


def _check(doc: dict, profile: Profile) -> None:
    summary = json.dumps({k: doc[k] for k in ("kills", "replicas", "versions", "learning", "packet_loss")}, default=str)[:4000]
    assert len(doc["kills"]) == len(profile.rollout_kills_s) + 2, summary
    assert doc["packet_loss"]["dropped_packets"] > 0, "the loss rules dropped nothing"
    for k in doc["kills"]:
        assert k["detect_launcher_s"] is not None and k["respawn_s"] is not None, k
        if k["was_running"]:  # (an incarnation killed while still starting has no token to lose)
            assert k["detect_liveliness_s"] is not None, k  # the kill was seen through its liveliness token
        assert k.get("latest_weights_s") is not None or k.get("superseded"), k
    assert doc["learning"]["learned_after_every_fault"], summary
    assert doc["versions"]["monotonic"], doc["versions"]
    assert doc["replicas"]["all_identical"], doc["replicas"]
    acct = doc["accounting"]
    assert acct["unaccounted"] == 0 and acct["lost_within_bounds"], acct
    assert acct["produced"] == acct["consumed"] + acct["dropped"] + acct["rejected"] + acct["lost"], acct
    assert doc["every_killed_rollout_accounted"], acct
    killed_actor = [x for x in acct["lost_by_incarnation"] if x["where"] == "actor"]
    assert len(killed_actor) == 1, acct
    assert doc["restarts"] and all(doc["restarts"][k["role"]] >= 1 for k in doc["kills"]), doc["restarts"]
    assert doc["ok"]


def _no_leftovers(run: str) -> None:
    prefix = run_prefix(run)
    assert not [n for n in list_netns() if n.startswith(prefix)]
    assert not [n for n in list_links() if n.startswith(prefix)]
    assert prefix not in subprocess.run(["tc", "qdisc", "show"], capture_output=True, text=True).stdout


@pytest.mark.timeout(900)
def test_chaos_short_profile(tmp_path: Path) -> None:
    doc = run_chaos(ROOT / "topologies" / "8node.yaml", QUICK, tmp_path / "runs", free_port_block())
    (tmp_path / "chaos.json").write_text(json.dumps(doc, indent=1, default=str))
    _check(doc, QUICK)
    _no_leftovers(doc["run"])


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_chaos_five_minutes(tmp_path: Path) -> None:
    doc = run_chaos(ROOT / "topologies" / "8node.yaml", FULL, tmp_path / "runs", free_port_block())
    _check(doc, FULL)
    _no_leftovers(doc["run"])

"""Hostile traffic against a running `dvla up` (tiny topology, loopback).

Without the run's credentials: a process forges weights, `stop` commands, status and eval reports
and snapshot replies on the control plane, sends well-formed poisoned chunks (NaN, -inf, a far
future version) under real rollouts' names, garbage, oversized payloads, 200 MB envelopes and puts
on 100,000 distinct keys on the data plane, queries status and snapshots unsigned, and replays
genuinely signed messages it captured (on their keys, moved to other weight senders' keys, and as
replies to the run's own queries).

Nothing may be applied: the run goes on (new versions), no role stops or restarts, versions stay
below the forged one everywhere and every replica at the actor's version holds its checksum; each
rejection is counted under its reason in the roles' status; memory stays bounded; status answers
within 2 s; and the run's chunk accounting still closes exactly (forged data is reported as
foreign, never as produced).

With the credentials of a *rollout* (read from its process, as an attacker who took it over
would): forged weights, commands, status queries, eval results and chunks under other names are
refused by every other role, and its own poisoned chunks never reach the learner."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dvla.fabric.fabric import UNAUTHENTICATED
from dvla.fabric.messages import Command

from .hostile import FORGED_VERSION, Attacker, poisoned_chunk, rss_kib
from .support import ROOT, free_port_block, harness_fabric, pids_of_run, start_up, state, statuses, wait_for

#: RSS growth allowed per role across the flood: a fraction of its size plus a constant
RSS_FACTOR, RSS_SLACK_KIB = 1.25, 64 * 1024


def _status_cli(runs: Path) -> dict:
    """`dvla status tiny -f json --timeout 2` in a process of its own: who answered, who stayed silent."""
    out = subprocess.run([sys.executable, "-m", "dvla", "status", "tiny", "--runs", str(runs), "-f", "json",
                          "--timeout", "2"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    doc = json.loads(out.stdout)
    return {"answered": sorted(r["name"] for r in doc["roles"]), "silent": doc["silent"]}


def _rejected(sts: dict, plane: str, reason: str) -> int:
    return sum(int(s.planes.get(plane, {}).get(f"rejected.{reason}", 0)) for s in sts.values())


@pytest.mark.timeout(600)
def test_hostile_traffic_is_refused_counted_and_harmless(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    run_dir = runs / "tiny"
    up = start_up("topologies/tiny.yaml", runs, "--base-port", str(free_port_block()), "--max-env-steps", "1000000000")
    fabric = None
    try:
        wait_for(lambda: state(run_dir).get("children"), 120, "the roles to start", up)
        fabric = harness_fabric(run_dir)
        roles = set(state(run_dir)["children"])

        def warm() -> dict | None:
            sts = statuses(fabric)
            actor = sts.get("actor-node0-0")
            ok = set(sts) == roles and actor is not None and actor.extra["published_version"] >= 3
            return sts if ok else None

        before = wait_for(warm, 300, "every role up and the actor at version 3", up)
        pids = {n: s.pid for n, s in before.items()}
        rss_before = {n: rss_kib(p) for n, p in pids.items()}
        v_before = before["actor-node0-0"].extra["published_version"]

        # The eval-result keys are spared here: a sustained flood there keeps the orchestrator's
        # small eval inbox full, so genuine evals arrive to a full inbox (dropped as backpressure,
        # counted); test_inbox_drains_past_forged_messages below checks that forged evals never
        # hide genuine ones that did get in.
        with Attacker.for_run(run_dir) as atk:
            atk.start_capture(evals=False)
            # A genuinely signed command for the attacker to capture and replay (`checkpoint` is
            # not acted on by any role: sending it changes nothing by itself).
            time.sleep(1.0)
            fabric.publish_ctrl(fabric.keys.cmd("all"), Command(target="all", verb="checkpoint", args={},
                                                                issued_ns=time.time_ns()))
            wait_for(lambda: atk.captured_count() >= 20, 60, "signed traffic to capture", up)
            assert atk.unsigned_queries() == 0, "an unsigned query got a reply"
            atk.many_keys(100_000)
            atk.huge_envelopes(200)
            sent = atk.flood(seconds=8.0, evals=False)
            replayed = atk.replay()
            moved = atk.moved_weights()
            # The operator's own `dvla status`, from a process of its own (the attacker is not in it):
            # every role answers within the query's 2 s even now.
            during = _status_cli(runs)
            sent.update(atk.flood(seconds=4.0, evals=False))
            replayed += atk.replay()
        assert replayed >= 20 and any(k.endswith("/cmd/all") for k, _ in atk.captured), "nothing signed was captured"
        assert moved > 0 and sent["forged_commands"] > 0 and sent["data_oversize"] > 0 and sent["data_forged_chunks"] > 0
        assert set(during["answered"]) == roles and during["silent"] == [], during

        # The run goes on: new versions after the flood, from the same processes.
        after = wait_for(lambda: (lambda s: s if set(s) == roles and s["actor-node0-0"].extra["published_version"]
                                  > v_before + 2 else None)(statuses(fabric)), 180, "new versions after the flood", up)
        assert up.poll() is None, "dvla up stopped"
        assert {n: s.pid for n, s in after.items()} == pids, "a role restarted"
        assert all(s.state == "running" for s in after.values()), {n: s.state for n, s in after.items()}
        actor = after["actor-node0-0"]
        v_actor = actor.extra["published_version"]
        # The actor's own version is what it has learned, which may be ahead of what its publish lane
        # has sent; no role may hold one it has not made (+1: the statuses are taken one by one).
        v_learned = actor.policy_version
        assert v_learned >= v_actor
        for name, s in after.items():
            assert s.policy_version < FORGED_VERSION, f"{name} applied forged weights"
            assert s.policy_version <= v_learned + 1, f"{name} holds v{s.policy_version} > the actor's v{v_learned}"
            if s.kind in ("rollout", "replicator") and s.extra.get("held_version") == v_actor:
                assert s.extra["held_checksum"] == actor.extra["published_checksum"], name

        # Each rejection is counted under its reason.
        assert _rejected(after, "ctrl", "key_id") >= sent["forged_commands"], "forged commands not counted"
        assert _rejected(after, "ctrl", "unsigned") > _rejected(before, "ctrl", "unsigned")
        assert _rejected(after, "ctrl", "malformed") > _rejected(before, "ctrl", "malformed")
        assert _rejected(after, "ctrl", "replay") + _rejected(after, "ctrl", "stale") > 0, "replays not refused"
        data = after["actor-node0-0"].planes["data"]
        assert data.get("rejected.key_id", 0) >= sent["data_forged_chunks"] // 4  # signed with another key
        assert data.get("rejected.unsigned", 0) >= sent["data_oversize"] // 2  # bare codec bytes
        assert data["rejected"] > sent["data_oversize"] + sent["data_forged_chunks"] // 2
        peers = data.get("peers", {})
        assert peers[UNAUTHENTICATED]["rejected"] > 0 and len(peers) < 100, sorted(peers)[:10]
        for rollout in (n for n in roles if n.startswith("rollout")):  # nothing counted as a real rollout's
            assert peers.get(rollout, {}).get("rejected", 0) == 0, (rollout, peers.get(rollout))

        # Memory stays bounded: the actor's grows by less than 64 MiB.
        for name, pid in pids.items():
            rss = rss_kib(pid)
            assert rss is not None and rss_before[name] is not None
            assert rss <= rss_before[name] * RSS_FACTOR + RSS_SLACK_KIB, f"{name}: RSS {rss_before[name]} -> {rss} KiB"
            if name == "actor-node0-0":
                assert rss - rss_before[name] < 64 * 1024, f"actor RSS {rss_before[name]} -> {rss} KiB"

        fabric.close()
        fabric = None
        up.send_signal(signal.SIGINT)
        out, _ = up.communicate(timeout=120)
    finally:
        if fabric is not None:
            fabric.close()
        if up.poll() is None:
            up.kill()
            up.wait()
    assert up.returncode in (0, 130), out
    result = json.loads((run_dir / "result.json").read_text())
    assert all(n == 0 for n in result["restarts"].values()), result["restarts"]
    acct = result["accounting"]
    assert acct["unaccounted"] == 0 and acct["lost"] == 0, acct
    assert acct["foreign_rejected"] > 0, acct  # the forged trajectories, not counted as produced
    with open(run_dir / "metrics.csv") as f:
        assert max(int(r["version"]) for r in csv.DictReader(f)) < FORGED_VERSION
    with open(run_dir / "evals.csv") as f:
        assert all(int(r["version"]) < FORGED_VERSION for r in csv.DictReader(f))
    _assert_checkpoint_finite(run_dir)
    assert pids_of_run(run_dir) == []


def _assert_checkpoint_finite(run_dir: Path) -> None:
    """The weights the actor published last (its final checkpoint) are all finite."""
    import torch
    from safetensors.torch import load_file

    manifest = json.loads((run_dir / "checkpoints" / "MANIFEST.json").read_text())
    tensors = load_file(run_dir / "checkpoints" / manifest["dir"] / "policy.safetensors")
    assert tensors and all(bool(torch.isfinite(t).all()) for t in tensors.values())


def _taken_over(run_dir: Path, victim: str) -> tuple[bytes, object]:
    """What an attacker who took a rollout over holds: the cluster secret and a credential issued
    to that rollout's name by the run's operator (as the launcher issues one to every role)."""
    from dvla.fabric.identity import Identity
    from dvla.fabric.signing import load_secret

    st = state(run_dir)
    operator = Identity.from_text(Path(st["operator_identity"]).read_text())
    return load_secret(st.get("secret_file")), operator.issue("rollout", victim)


@pytest.mark.timeout(600)
def test_a_compromised_rollout_cannot_speak_for_other_roles(tmp_path: Path) -> None:
    import numpy as np

    from dvla.fabric import Fabric, plane_config
    from dvla.fabric.messages import EvalResult, RoleStatus, WeightChunk, WeightManifest

    runs = tmp_path / "runs"
    run_dir = runs / "tiny"
    up = start_up("topologies/tiny.yaml", runs, "--base-port", str(free_port_block()), "--max-env-steps", "1000000000")
    fabric = evil = None
    try:
        wait_for(lambda: state(run_dir).get("children"), 120, "the roles to start", up)
        fabric = harness_fabric(run_dir)
        roles = set(state(run_dir)["children"])
        before = wait_for(lambda: (lambda s: s if set(s) == roles and s["actor-node0-0"].extra["published_version"] >= 2
                                   else None)(statuses(fabric)), 300, "every role up and the actor at version 2", up)
        victim = "rollout-node0-0"
        secret, identity = _taken_over(run_dir, victim)
        cfg = json.loads((run_dir / "roles" / f"{victim}.json").read_text())
        evil = Fabric(run="tiny", name=victim, secret=secret, identity=identity,
                      ctrl_conf=plane_config(mode="client", connect=cfg["ctrl"]["connect"]),
                      data_conf=plane_config(mode="peer", connect=cfg["data"]["connect"]))
        keys = evil.keys
        time.sleep(2.0)
        v_before = before["actor-node0-0"].extra["published_version"]
        for _ in range(5):
            for sender in ("actor-node0-0", "replicator-node0-0"):
                man = WeightManifest(sender=sender, version=FORGED_VERSION, base_version=-1, encoding="full",
                                     layout_hash="0" * 16, checksum="0" * 16, n_chunks=1, total_bytes=16)
                evil.publish_ctrl(keys.weights(sender), man, weights=True, sign_key=keys.weights_signed())
                evil.publish_ctrl(keys.weights(sender), WeightChunk(sender=sender, version=FORGED_VERSION, index=0,
                                                                    n_chunks=1, data=bytes(16)),
                                  weights=True, sign_key=keys.weights_signed())
            evil.publish_ctrl(keys.cmd("all"), Command(target="all", verb="stop", args={}))
            evil.publish_ctrl(keys.eval("evaluator-node0-0"), EvalResult(
                sender="evaluator-node0-0", policy_version=FORGED_VERSION, episodes=1, success_once=1.0,
                success_at_end=1.0, return_mean=1e9))
            evil.publish_ctrl(keys.status("actor-node0-0"), RoleStatus(
                name="actor-node0-0", kind="actor", node="x", rack="x", pid=1, state="error",
                policy_version=FORGED_VERSION, env_steps=0, steps_per_s=0.0))
            assert evil.query(keys.status_all(), expect=RoleStatus, timeout=1.0) == []  # only the operator asks
            time.sleep(0.3)
        # Its own trajectory key: authentic, but poisoned values never reach the learner.
        from dvla.config import RoleConfig
        from dvla.learn.envs import probe_spec

        obs_spec, act_dim = probe_spec(RoleConfig.from_json((run_dir / "roles" / f"{victim}.json").read_text()).task)
        dim = int(np.prod(obs_spec["state"].shape))
        n_envs = cfg["task"]["envs_per_rollout"]
        for version in (0, FORGED_VERSION):
            chunk = poisoned_chunk(victim, dim, act_dim, version, t=cfg["task"]["chunk_steps"], n=n_envs)
            evil.publish_traj(chunk)
        time.sleep(3.0)

        after = wait_for(lambda: (lambda s: s if set(s) == roles and s["actor-node0-0"].extra["published_version"]
                                  > v_before + 1 else None)(statuses(fabric)), 180, "new versions after the attack", up)
        assert up.poll() is None and all(s.state == "running" for s in after.values())
        assert {n: s.pid for n, s in after.items()} == {n: s.pid for n, s in before.items()}, "a role restarted"
        for name, s in after.items():
            assert s.policy_version < FORGED_VERSION, f"{name} applied forged weights"
        unauthorized = {n: int(s.planes.get("ctrl", {}).get("rejected.unauthorized", 0)) for n, s in after.items()}
        for name in roles - {victim}:  # every other role refused the commands (and more)
            assert unauthorized[name] >= 5, unauthorized
        data = after["actor-node0-0"].planes["data"]
        assert data.get("rejected.nonfinite", 0) + data.get("rejected.future_version", 0) >= 2, data
    finally:
        for f in (evil, fabric):
            if f is not None:
                f.close()
        if up.poll() is None:
            up.send_signal(signal.SIGINT)
            try:
                up.communicate(timeout=120)
            except Exception:
                up.kill()
                up.wait()
    assert pids_of_run(run_dir) == []


@pytest.mark.timeout(120)
def test_inbox_drains_past_forged_messages() -> None:
    import os

    import zenoh

    from dvla.fabric import Fabric, plane_config
    from dvla.fabric.messages import EvalResult

    port = free_port_block(1)
    ep = (f"tcp/127.0.0.1:{port}",)
    with Fabric(run="hostile", name="monitor", ctrl_conf=plane_config(mode="peer", listen=ep), data_conf=None,
                secret=os.urandom(32)) as victim:
        inbox = victim.subscribe_ctrl(victim.keys.eval_all(), 4, EvalResult, block_s=0.2)
        attacker = zenoh.open(plane_config(mode="peer", connect=ep))
        try:
            wait_for(lambda: attacker.declare_publisher(victim.keys.eval("evaluator-x")).matching_status.matching,
                     10, "the subscription to reach the attacker")
            for _ in range(4):
                attacker.put(victim.keys.eval("evaluator-x"), os.urandom(100))
            wait_for(lambda: inbox.depth() == 4, 10, "the forged messages to arrive")
            assert inbox.get_nowait() is None  # nothing valid
            assert inbox.depth() == 0, "one get_nowait left forged messages queued"
        finally:
            attacker.close()

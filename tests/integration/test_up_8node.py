"""`dvla up topologies/8node.yaml` on the emulated cluster (a network namespace per node, rate
limited links): `dvla status` sees all 8 nodes with their racks, roles, versions and steps/s,
learning progresses (versions advance and reach every rollout), and after Ctrl-C nothing of the
run is left: no namespace, veth, bridge, qdisc or process."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dvla.orchestrator.netns import list_links, list_netns, run_prefix

from .test_netns import _netns_usable
from .test_up_e2e import ROOT, dvla, pids_of_run

pytestmark = [
    pytest.mark.netns,
    pytest.mark.skipif(not _netns_usable(), reason="needs root and `ip netns`"),
]


def _status(runs: Path) -> dict:
    st = dvla("status", "cluster8", "--runs", str(runs), "--format", "json", timeout=60)
    return json.loads(st.stdout) if st.returncode == 0 else {}


@pytest.mark.timeout(420)
def test_8node_cluster_runs_shows_every_node_and_cleans_up(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    up = subprocess.Popen(
        [sys.executable, "-m", "dvla", "up", "topologies/8node.yaml", "--runs", str(runs),
         "--max-env-steps", "200000", "--quiet"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    prefix = run_prefix("cluster8")
    try:
        doc: dict = {}
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            assert up.poll() is None, "dvla up exited early:\n" + (up.stdout.read() if up.stdout else "")
            doc = _status(runs)
            rollouts = [r for r in doc.get("roles", []) if r["kind"] == "rollout"]
            actor = [r for r in doc.get("roles", []) if r["kind"] == "actor"]
            if (
                len(doc.get("roles", [])) == 12 and len(rollouts) == 8 and actor and actor[0]["extra"].get("published_version", 0) >= 3
                and all(r["policy_version"] >= 2 and r["env_steps"] > 0 for r in rollouts)
            ):
                break
            time.sleep(2.0)
        else:
            pytest.fail(f"the cluster did not reach version 3 on every rollout: {json.dumps(doc)[:2000]}")
        roles = doc["roles"]
        nodes = {r["node"]: r["rack"] for r in roles}
        assert nodes == {f"r{r}n{n}": f"r{r}" for r in range(2) for n in range(4)}
        kinds = sorted(r["kind"] for r in roles)
        assert kinds == ["actor", "evaluator", "replicator", "replicator"] + ["rollout"] * 8
        assert all(math.isfinite(r["steps_per_s"]) and r["state"] == "running" for r in roles)
        # The table names every node too.
        table = dvla("status", "cluster8", "--runs", str(runs), timeout=60).stdout
        assert all(f"r{r}n{n}" in table for r in range(2) for n in range(4))
        # Every namespace of the run exists while it is up.
        assert len([n for n in list_netns() if n.startswith(prefix)]) == 9  # 8 nodes + the fabric
        up.send_signal(signal.SIGINT)
        out, _ = up.communicate(timeout=120)
        assert up.returncode in (0, 130), out
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    run_dir = runs / "cluster8"
    result = json.loads((run_dir / "result.json").read_text())
    assert result["final_version"] >= 3
    assert result["accounting"]["unaccounted"] == 0, result["accounting"]
    assert not [n for n in list_netns() if n.startswith(prefix)]
    assert not [n for n in list_links() if n.startswith(prefix)]
    assert not pids_of_run(run_dir)
    tc = subprocess.run(["tc", "qdisc", "show"], capture_output=True, text=True).stdout
    assert prefix not in tc

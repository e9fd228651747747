"""The embedding example (examples/embed_gym_loop.py) against a real dvla actor process.

The actor runs as `python -m dvla.roles.actor --config cfg.json` with a Pendulum task whose env
is the example's own factory; the example (a plain Gymnasium loop with its own Fabric) ships a
few thousand env steps and loads the weight versions the actor publishes. Checked: the actor
learned from the chunks (its status reports env_steps > 0) and the example loaded at least two
versions whose checksum, recomputed from its own policy, matches the actor's manifest.
"""

from __future__ import annotations

import importlib
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Iterator

import pytest

from dvla.fabric import Fabric, RoleStatus, new_secret, plane_config

ROOT = Path(__file__).resolve().parents[2]


def free_port_pair() -> int:
    """A port p with p and p + 1 free right now."""
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        try:
            with socket.socket() as t:
                t.bind(("127.0.0.1", base + 1))
            return base
        except OSError:
            continue
    raise RuntimeError("no two consecutive free ports")


@pytest.fixture(scope="module")
def example():
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    return importlib.import_module("examples.embed_gym_loop")


@pytest.fixture
def actor(example, tmp_path: Path) -> Iterator[dict]:
    port = free_port_pair()
    cfg = example.actor_config(str(tmp_path / "run"), port, run="embedtest")
    cfg_path = tmp_path / "actor.json"
    cfg_path.write_text(cfg.to_json())
    secret = new_secret()
    env = {**os.environ, "DVLA_SECRET": secret, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    log = (tmp_path / "actor.log").open("w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "dvla.roles.actor", "--config", str(cfg_path)],
        cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
    )
    try:
        yield {
            "proc": proc, "name": cfg.name, "run": cfg.run, "secret": bytes.fromhex(secret),
            "ctrl": cfg.ctrl.listen[0], "data": cfg.data.listen[0], "log": tmp_path / "actor.log",
        }
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
        log.close()


def actor_status(actor: dict) -> RoleStatus:
    tool = Fabric(
        run=actor["run"], name="embed-test", secret=actor["secret"], data_conf=None,
        ctrl_conf=plane_config(mode="client", connect=[actor["ctrl"]]), open_timeout_s=10.0,
    )
    try:
        replies = tool.query(tool.keys.status(actor["name"]), expect=RoleStatus, timeout=5.0)
    finally:
        tool.close()
    assert replies, "the actor did not answer its status query"
    return replies[0][1]


@pytest.mark.timeout(240)
def test_gym_loop_feeds_a_real_actor_and_loads_its_weights(example, actor: dict) -> None:
    summary = example.run(
        ctrl=actor["ctrl"], data=actor["data"], run_id=actor["run"], actor=actor["name"],
        steps=3000, min_versions=2, max_wall_s=150.0, secret=actor["secret"],
    )
    log = actor["log"].read_text(errors="replace")[-3000:]
    assert actor["proc"].poll() is None, f"the actor died:\n{log}"
    assert summary["env_steps"] >= 3000, summary
    versions = summary["versions"]
    assert len(versions) >= 2, f"{summary}\n{log}"
    for v in versions:
        assert v["policy_checksum"] == v["manifest_checksum"], v
    assert [v["version"] for v in versions] == sorted({v["version"] for v in versions})
    assert summary["weights_rejected"] == 0

    st = actor_status(actor)
    assert st.env_steps > 0, st
    assert st.policy_version >= 2
    data = st.planes.get("data", {})
    assert data.get("received", 0) > 0 and data.get("rejected", 0) == 0, data

    actor["proc"].send_signal(signal.SIGTERM)
    assert actor["proc"].wait(timeout=30) == 0, log

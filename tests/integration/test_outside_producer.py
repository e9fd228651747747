"""A producer that is not dvla joins a live `dvla up` with a credential from `dvla identity issue`.

tests/outside/producer.py imports nothing from dvla: it was written from docs/wire-format.md
(msgpack messages, envelopes with an identity block, the credential format). Against a Pendulum run
(one actor, one rollout): with an issued credential its signed snapshot query is answered (it sees a version)
and the actor accounts every chunk it sends as received from its name; with a credential from
another operator, and with its own credential after `dvla identity revoke`, its chunks are
refused and counted (`bad_identity`, `revoked`) under `<unauthenticated>`. Then, as a robot
that only dials out: the same producer as a Zenoh client of one bare router per plane
(tests/outside/router.py, connected to the actor), with the same result as a direct peer; and
`dvla join` (dvla's own rollout from an issued credential) through those routers, learned from
before and after they are killed and restarted, and through the routers `dvla up` starts for the
topology's `router:`.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

import pytest

from benchmarks.ports import free_port_block
from dvla.fabric.identity import Identity

ROOT = Path(__file__).resolve().parents[2]
RUN = "outside"
ACTOR = "actor-node0-0"
N_CHUNKS = 20
T = 10

TOPOLOGY = f"""
run: {RUN}
task:
  env: "examples.embed_gym_loop:make_pendulum"
  max_episode_steps: 200
  policy: mlp
  policy_kwargs: {{hidden: [16, 16]}}
  envs_per_rollout: 2
  chunk_steps: {T}
  device: cpu
  ppo: {{batch_steps: 100, minibatches: 2, update_epochs: 1}}
  budget: {{max_env_steps: 100000000}}
racks:
  - name: rack0
    nodes:
      - name: node0
        host: localhost
        roles:
          - role: actor
          - role: rollout
"""


def dvla(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dvla", *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=timeout)


def produce(ctrl: str, data: str, runs: Path, credential: Path, wait_s: float, data_mode: str = "peer") -> dict:
    state = json.loads((runs / RUN / "state.json").read_text())
    secret = state.get("secret_file") or str(runs / RUN / "secret")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # nothing of dvla on its path
    out = subprocess.run(
        [sys.executable, str(ROOT / "tests/outside/producer.py"), RUN, ctrl, data, secret, str(credential), ACTOR,
         str(N_CHUNKS), str(T), str(wait_s), data_mode],
        capture_output=True, text=True, cwd=credential.parent, env=env, timeout=90)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def actor_data(runs: Path) -> dict:
    for _ in range(3):  # on a loaded machine the tool's session may time out joining the ctrl plane
        st = dvla("status", RUN, "--runs", str(runs), "--format", "json")
        if st.returncode == 0:
            break
    assert st.returncode == 0, st.stderr
    (actor,) = [r for r in json.loads(st.stdout)["roles"] if r["name"] == ACTOR]
    return actor["planes"]["data"]


def wait_for(check, timeout: float = 20.0):
    deadline = time.monotonic() + timeout
    while True:
        got = check()
        if got or time.monotonic() > deadline:
            return got
        # most checks start a `dvla status` (~1 s of CPU): polled back to back they took a core
        # from the run they wait on
        time.sleep(3.0)


@pytest.fixture(scope="module")
def live_run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, int]]:
    """(runs directory, base port) of a live `dvla up` of TOPOLOGY."""
    tmp = tmp_path_factory.mktemp("outside")
    runs, port = tmp / "runs", free_port_block()
    topo = tmp / "outside.yaml"
    edge = free_port_block(2)  # node0's routers (`router:`), for `dvla join` without --connect-*
    topo.write_text(TOPOLOGY + f"        router: {{ctrl: {edge}, data: {edge + 1}}}\n")
    up = subprocess.Popen([sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs), "--base-port", str(port),
                           "--quiet"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert wait_for(lambda: (runs / RUN / "state.json").exists() or up.poll() is not None, 90)
        assert up.poll() is None, up.communicate()[0]
        yield runs, port
    finally:
        if up.poll() is None:
            dvla("down", RUN, "--runs", str(runs), timeout=90)
        if up.poll() is None:
            up.kill()
        up.wait()


def issue(runs: Path, name: str) -> Path:
    path = runs.parent / f"{name}.id"
    res = dvla("identity", "issue", RUN, "--kind", "rollout", "--name", name, "-o", str(path), "--runs", str(runs))
    assert res.returncode == 0, res.stderr
    return path


def received(runs: Path, name: str) -> int:
    return actor_data(runs).get("peers", {}).get(name, {}).get("received", 0)


@pytest.mark.timeout(240)
def test_outside_producer_with_issued_foreign_and_revoked_credentials(live_run: tuple[Path, int]) -> None:
    runs, port = live_run
    issued = issue(runs, "robot-1")
    got = produce(f"tcp/127.0.0.1:{port}", f"tcp/127.0.0.1:{port + 1}", runs, issued, wait_s=60)
    assert got["version"] >= 1 and got["sent"] == N_CHUNKS, got  # its signed query was answered
    assert wait_for(lambda: received(runs, "robot-1") >= N_CHUNKS)
    data = actor_data(runs)
    assert data["peers"]["robot-1"]["received"] == N_CHUNKS, data
    assert not any(k.startswith("rejected") for k in data["peers"]["robot-1"]), data

    foreign = runs.parent / "foreign.id"
    foreign.write_text(Identity.operator(RUN).issue("rollout", "robot-2").to_text())
    got = produce(f"tcp/127.0.0.1:{port}", f"tcp/127.0.0.1:{port + 1}", runs, foreign, wait_s=3)
    assert got["version"] == -1  # its query was refused: no reply
    unauth = lambda key: actor_data(runs).get("peers", {}).get("<unauthenticated>", {}).get(key, 0)  # noqa: E731
    assert wait_for(lambda: unauth("rejected.bad_identity") >= N_CHUNKS), actor_data(runs)

    res = dvla("identity", "revoke", RUN, "robot-1", "--runs", str(runs))
    assert res.returncode == 0 and "every live role" in res.stdout, res.stderr
    got = produce(f"tcp/127.0.0.1:{port}", f"tcp/127.0.0.1:{port + 1}", runs, issued, wait_s=3)
    assert got["version"] == -1
    assert wait_for(lambda: unauth("rejected.revoked") >= N_CHUNKS), actor_data(runs)
    assert received(runs, "robot-1") == N_CHUNKS  # nothing more accepted


@pytest.mark.timeout(180)
def test_outside_producer_as_a_zenoh_client_through_routers(live_run: tuple[Path, int]) -> None:
    # The robot dials out only, to one router per plane (a site's edge), never to the actor.
    runs, port = live_run
    edge = free_port_block(2)
    routers = [subprocess.Popen([sys.executable, str(ROOT / "tests/outside/router.py"), f"tcp/127.0.0.1:{edge + i}",
                                 f"tcp/127.0.0.1:{port + i}"], stdout=subprocess.PIPE, text=True) for i in (0, 1)]
    try:
        for r in routers:
            assert r.stdout.readline().strip() == "ready"
        cred = issue(runs, "robot-3")
        got = produce(f"tcp/127.0.0.1:{edge}", f"tcp/127.0.0.1:{edge + 1}", runs, cred, wait_s=60, data_mode="client")
        assert got["version"] >= 1 and got["sent"] == N_CHUNKS, got
        assert wait_for(lambda: received(runs, "robot-3") >= N_CHUNKS), actor_data(runs)
        assert received(runs, "robot-3") == N_CHUNKS
    finally:
        for r in routers:
            r.kill()
            r.wait()


def start_routers(edge: int, port: int) -> list[subprocess.Popen]:
    """One bare router per plane on edge, edge + 1, each connected to the actor's plane."""
    routers = [subprocess.Popen([sys.executable, str(ROOT / "tests/outside/router.py"), f"tcp/127.0.0.1:{edge + i}",
                                 f"tcp/127.0.0.1:{port + i}"], stdout=subprocess.PIPE, text=True) for i in (0, 1)]
    for r in routers:
        assert r.stdout.readline().strip() == "ready"
    return routers


def stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
        p.wait()


def role_status(runs: Path, name: str) -> dict | None:
    st = dvla("status", RUN, "--runs", str(runs), "--format", "json")
    return next((r for r in json.loads(st.stdout)["roles"] if r["name"] == name), None) if st.returncode == 0 else None


@pytest.mark.timeout(240)
def test_dvla_join_runs_a_rollout_through_routers_and_survives_their_restart(live_run: tuple[Path, int]) -> None:
    # `dvla join`: dvla's own rollout, from an issued credential, dialing out to the routers only.
    runs, port = live_run
    edge = free_port_block(2)
    routers = start_routers(edge, port)
    cred = issue(runs, "robot-4")
    topo = runs.parent / "outside.yaml"
    robot = subprocess.Popen([sys.executable, "-m", "dvla", "join", str(topo), "--credential", str(cred), "--runs", str(runs),
                              "--connect-ctrl", f"tcp/127.0.0.1:{edge}", "--connect-data", f"tcp/127.0.0.1:{edge + 1}"],
                             cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert wait_for(lambda: received(runs, "robot-4") >= 5 or robot.poll() is not None, 90), actor_data(runs)
        assert robot.poll() is None, robot.communicate()[0]
        st = wait_for(lambda: (s := role_status(runs, "robot-4")) and s["policy_version"] >= 1 and s, 30)
        assert st and st["kind"] == "rollout", st  # versions reach it through the ctrl router
        consumed = lambda: actor_data(runs)["peers"]["robot-4"].get("consumed", 0)  # noqa: E731
        assert wait_for(lambda: consumed() >= 1), actor_data(runs)  # learned from, not only received
        stop(routers)  # the link is lost: the rollout blocks, its client session retries
        time.sleep(5)
        before = consumed()
        routers = start_routers(edge, port)
        assert wait_for(lambda: consumed() >= before + 5 or robot.poll() is not None, 90), actor_data(runs)
        assert robot.poll() is None, robot.communicate()[0]
        peer = actor_data(runs)["peers"]["robot-4"]
        # too old for the learner (`dropped.stale`) is a count of its own; nothing is refused
        assert not any(k.startswith("rejected") for k in peer), peer
    finally:
        robot.terminate()
        out = robot.communicate(timeout=60)[0]
        stop(routers)
    assert robot.returncode == 0, out[-3000:]


@pytest.mark.timeout(180)
def test_dvla_join_dials_the_routers_dvla_up_started_for_the_topology(live_run: tuple[Path, int]) -> None:
    runs, _port = live_run
    linked = lambda s: s and s["state"] == "running" and min(s["extra"]["linked"].values()) >= 1  # noqa: E731
    router = wait_for(lambda: (s := role_status(runs, "router-node0-0")) and linked(s) and s, 30)
    assert router and router["kind"] == "router", role_status(runs, "router-node0-0")
    cred = issue(runs, "robot-5")
    # The robot's own run directory is not the run's (no shared file system): only the secret is copied.
    robot_runs = runs.parent / "robot-machine"
    secret = json.loads((runs / RUN / "state.json").read_text()).get("secret_file") or str(runs / RUN / "secret")
    robot = subprocess.Popen([sys.executable, "-m", "dvla", "join", str(runs.parent / "outside.yaml"), "--credential",
                              str(cred), "--runs", str(robot_runs), "--secret", secret], cwd=ROOT,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        consumed = lambda: actor_data(runs).get("peers", {}).get("robot-5", {}).get("consumed", 0)  # noqa: E731
        assert wait_for(lambda: consumed() >= 5 or robot.poll() is not None, 90), actor_data(runs)
        assert robot.poll() is None, robot.communicate()[0]
        st = wait_for(lambda: (s := role_status(runs, "robot-5")) and s["policy_version"] >= 1 and s, 30)
        assert st, role_status(runs, "robot-5")
    finally:
        robot.terminate()
        out = robot.communicate(timeout=60)[0]
    assert robot.returncode == 0, out[-3000:]
    assert f"through ctrl tcp/127.0.0.1:{router['extra']['listen']['ctrl'][0].rsplit(':', 1)[1]}" in out, out[:500]
    # Its counter file is on its machine; the learner keeps the run's copy, up to its clean last record.
    (own,) = (robot_runs / RUN / "counters").glob("robot-5.*")
    mine = json.loads(own.read_text())
    assert mine["clean"] and mine["shipped"] >= 5, mine
    copy = runs / RUN / "counters" / own.name
    assert wait_for(lambda: copy.exists() and json.loads(copy.read_text())["clean"], 15), list(copy.parent.iterdir())
    assert json.loads(copy.read_text()) == mine

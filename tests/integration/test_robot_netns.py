"""A robot behind NAT as a rollout: a network namespace that drops every inbound connection
(iptables: only ESTABLISHED,RELATED comes in) runs `dvla join`, reaching the run only through the
routers `dvla up` starts for the topology's `router:`; its link is cut for 10 s in the middle of
a run of over 2 minutes. Chunks from before and after the cut are consumed, versions reach the
robot after it, and the run's accounting has nothing unaccounted: the chunks that were in the
cut link's buffers are lost with it (the robot saw its link break; the ledger places the gap
there, within the buffers' bound). The robot keeps its own run directory, as on a machine of its
own: its counter record reaches the run through the learner. Needs root, `ip netns` and
iptables."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.ports import free_port_block

ROOT = Path(__file__).resolve().parents[2]
RUN = f"robotns-{os.getpid()}"
NS = f"dvrobot{os.getpid() % 100000}"
HOST_END, ROBOT_END = f"dvh{os.getpid() % 100000}", f"dvr{os.getpid() % 100000}"
#: a /24 of its own, outside netns.py's 10.77.0.0/16
HOST_IP, ROBOT_IP = "10.213.7.1", "10.213.7.2"
CUT_S = 10


def _usable() -> bool:
    if os.geteuid() != 0 or not shutil.which("ip") or not shutil.which("iptables"):
        return False
    return subprocess.run(["ip", "netns", "list"], capture_output=True).returncode == 0


pytestmark = [pytest.mark.netns, pytest.mark.slow,
              pytest.mark.skipif(not _usable(), reason="needs root, `ip netns` and iptables")]


def sh(*args: str) -> None:
    subprocess.run(args, check=True, capture_output=True, text=True)


def in_ns(*args: str) -> list[str]:
    return ["ip", "netns", "exec", NS, *args]


def dvla(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dvla", *args], capture_output=True, text=True, cwd=ROOT, timeout=timeout)


def status(runs: Path) -> dict[str, dict]:
    for _ in range(3):
        st = dvla("status", RUN, "--runs", str(runs), "--format", "json")
        if st.returncode == 0:
            return {r["name"]: r for r in json.loads(st.stdout)["roles"]}
    raise AssertionError(st.stderr)


def consumed(runs: Path) -> int:
    return status(runs)["actor-node0-0"]["planes"]["data"].get("peers", {}).get("robot-1", {}).get("consumed", 0)


def wait_for(check, timeout: float):
    deadline = time.monotonic() + timeout
    while not (got := check()) and time.monotonic() < deadline:
        time.sleep(1.0)
    return got


@pytest.fixture
def robot_ns():
    """The robot's namespace: one veth to this host, inbound connections dropped."""
    subprocess.run(["ip", "netns", "del", NS], capture_output=True)
    try:
        sh("ip", "netns", "add", NS)
        sh("ip", "link", "add", HOST_END, "type", "veth", "peer", "name", ROBOT_END)
        sh("ip", "link", "set", ROBOT_END, "netns", NS)
        sh("ip", "addr", "add", f"{HOST_IP}/24", "dev", HOST_END)
        sh("ip", "link", "set", HOST_END, "up")
        sh(*in_ns("ip", "addr", "add", f"{ROBOT_IP}/24", "dev", ROBOT_END))
        sh(*in_ns("ip", "link", "set", ROBOT_END, "up"))
        sh(*in_ns("ip", "link", "set", "lo", "up"))
        sh(*in_ns("iptables", "-A", "INPUT", "-i", "lo", "-j", "ACCEPT"))
        sh(*in_ns("iptables", "-A", "INPUT", "-m", "conntrack", "--ctstate", "ESTABLISHED,RELATED", "-j", "ACCEPT"))
        sh(*in_ns("iptables", "-A", "INPUT", "-j", "DROP"))
        yield
    finally:
        subprocess.run(["ip", "link", "del", HOST_END], capture_output=True)
        subprocess.run(["ip", "netns", "del", NS], capture_output=True)
        assert NS not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout


def test_robot_behind_nat_survives_a_cut_link(tmp_path: Path, robot_ns: None) -> None:
    runs, base, edge = tmp_path / "runs", free_port_block(), free_port_block(2)
    topo = tmp_path / "robot.yaml"
    topo.write_text(f"""
run: {RUN}
task:
  env: "examples.embed_gym_loop:make_pendulum"
  max_episode_steps: 200
  policy: mlp
  policy_kwargs: {{hidden: [16, 16]}}
  envs_per_rollout: 2
  chunk_steps: 10
  device: cpu
  ppo: {{batch_steps: 200, minibatches: 2, update_epochs: 1}}
  budget: {{max_env_steps: 100000000}}
racks:
  - name: rack0
    nodes:
      - name: node0
        host: localhost
        roles: [{{role: actor}}, {{role: rollout}}]
        router: {{ctrl: {edge}, data: {edge + 1}, address: 0.0.0.0}}
""")
    up = subprocess.Popen([sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs), "--base-port", str(base),
                           "--quiet"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    robot = None
    try:
        assert wait_for(lambda: (runs / RUN / "state.json").exists() or up.poll() is not None, 90)
        assert up.poll() is None, up.communicate()[0]
        # Inbound is dropped: this host cannot open a connection into the robot's namespace.
        listener = subprocess.Popen(in_ns(sys.executable, "-c", f"import socket,time; s=socket.socket(); "
                                          f"s.bind(('{ROBOT_IP}', {edge})); s.listen(); print('ok', flush=True); "
                                          "time.sleep(30)"), stdout=subprocess.PIPE, text=True)
        assert listener.stdout.readline().strip() == "ok"
        probe = subprocess.run([sys.executable, "-c", f"import socket; socket.create_connection(('{ROBOT_IP}', {edge}), 3)"],
                               capture_output=True, text=True)
        listener.kill()
        listener.wait()
        assert probe.returncode != 0 and "timed out" in probe.stderr, probe.stderr
        # The actor's own listeners are on this host's loopback: out of the robot's reach.
        direct = subprocess.run(in_ns(sys.executable, "-c", f"import socket; socket.create_connection(('{HOST_IP}', {base}), 3)"),
                                capture_output=True, text=True)
        assert direct.returncode != 0, "the robot reached the actor without the router"

        cred = tmp_path / "robot-1.id"
        res = dvla("identity", "issue", RUN, "--kind", "rollout", "--name", "robot-1", "-o", str(cred), "--runs", str(runs))
        assert res.returncode == 0, res.stderr
        # The robot's run directory is its own (no shared file system): its counter record reaches
        # the run's accounting through the learner.
        secret = json.loads((runs / RUN / "state.json").read_text()).get("secret_file") or str(runs / RUN / "secret")
        robot = subprocess.Popen(in_ns(sys.executable, "-m", "dvla", "join", str(topo), "--credential", str(cred),
                                       "--runs", str(tmp_path / "robot-machine"), "--secret", secret,
                                       "--connect-ctrl", f"tcp/{HOST_IP}:{edge}",
                                       "--connect-data", f"tcp/{HOST_IP}:{edge + 1}"),
                                 cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        t0 = time.monotonic()
        assert wait_for(lambda: consumed(runs) >= 10 or robot.poll() is not None, 90)
        assert robot.poll() is None, robot.communicate()[0][-3000:]
        time.sleep(max(0.0, 55 - (time.monotonic() - t0)))
        before_chunks = consumed(runs)
        before_version = status(runs)["robot-1"]["policy_version"]
        sh("ip", "link", "set", HOST_END, "down")  # the robot's link is cut
        time.sleep(CUT_S)
        sh("ip", "link", "set", HOST_END, "up")
        t_up = time.monotonic()
        assert wait_for(lambda: consumed(runs) >= before_chunks + 10 or robot.poll() is not None, 90)
        resumed_s = time.monotonic() - t_up  # reported: the data link's BLOCK wait closes the dead link
        assert robot.poll() is None, robot.communicate()[0][-3000:]
        assert wait_for(lambda: status(runs).get("robot-1", {}).get("policy_version", -1) > before_version, 60)
        time.sleep(max(0.0, 125 - (time.monotonic() - t0)))  # over 2 minutes of the robot in all
        after = status(runs)
        assert after["actor-node0-0"]["planes"]["data"]["peers"]["robot-1"]["consumed"] > before_chunks + 10
        robot.terminate()
        out = robot.communicate(timeout=60)[0]
        assert robot.returncode == 0, out[-3000:]
        robot = None
        res = dvla("down", RUN, "--runs", str(runs), timeout=120)
        assert res.returncode == 0, res.stderr
        up.wait(timeout=60)
        acct = json.loads((runs / RUN / "result.json").read_text())["accounting"]
        (runs.parent / "robot.log").write_text(out)
        print(json.dumps({"robot_consumed_before_cut": before_chunks, "resumed_after_link_up_s": round(resumed_s, 1),
                          "accounting": acct}))
        assert acct["consumed"] > 0 and acct["unaccounted"] == 0 and acct["notes"] == [], acct
        assert [p.name for p in (runs / RUN / "counters").glob("robot-1.*")] == \
            [p.name for p in (tmp_path / "robot-machine" / RUN / "counters").glob("robot-1.*")]  # the learner's copy
        assert acct["lost_within_bounds"], acct
        # what was lost went with the robot's link (nothing was killed)
        assert {x["where"] for x in acct["lost_by_incarnation"]} <= {"link"}, acct
        assert all(x["role"] == "robot-1" for x in acct["lost_by_incarnation"]), acct
    finally:
        if robot is not None:
            robot.kill()
            robot.wait()
        if up.poll() is None:
            dvla("down", RUN, "--runs", str(runs), timeout=90)
        if up.poll() is None:
            up.kill()
        up.wait()

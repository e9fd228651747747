"""Remote nodes over SSH, against a real sshd: a network namespace stands in for a remote host.

The fixture builds one namespace joined to this one by a veth pair, runs OpenSSH's sshd inside it
on its own address with a freshly generated host key and a throwaway authorized_keys, and writes a
known_hosts file for it (so host-key checking is real too). Then `dvla up` runs a topology whose
actor is local and whose rollout lives on the "remote" host: it starts over SSH, trains with the
actor across the veth, and its summary comes back into the local run directory. Everything the
fixture made (sshd, namespace, veth, keys) is removed afterwards, and no process of a run is left.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .test_up_e2e import free_port_block

ROOT = Path(__file__).resolve().parents[2]
SSHD = "/usr/sbin/sshd"
SSH_PORT = 2222
TAG = os.getpid() % 100000
NETNS = f"dvssh{TAG}"
HOST_IF = f"dvsh{TAG}h"
SUBNET_OCTET = 100 + TAG % 100
LOCAL_IP = f"10.78.{SUBNET_OCTET}.1"
REMOTE_IP = f"10.78.{SUBNET_OCTET}.2"


def _usable() -> tuple[bool, str]:
    if os.geteuid() != 0:
        return False, "needs root"
    for tool in ("ip", "ssh", "ssh-keygen"):
        if shutil.which(tool) is None:
            return False, f"needs {tool}"
    if not os.path.exists(SSHD):
        return False, f"needs {SSHD} (apt-get install openssh-server; scripts/setup.sh does)"
    if subprocess.run(["ip", "netns", "list"], capture_output=True).returncode != 0:
        return False, "needs `ip netns`"
    return True, ""


_OK, _WHY = _usable()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(not _OK, reason=_WHY)]


def _sh(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=30)


def _wait_port(ip: str, port: int, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((ip, port), timeout=1):
                return
        except OSError:
            time.sleep(0.1)
    raise TimeoutError(f"nothing listens on {ip}:{port} after {timeout} s")


class RemoteHost:
    """The namespace, its sshd and the client's key material."""

    def __init__(self, base: Path) -> None:
        self.base = base
        self.key = base / "id_ed25519"
        self.wrong_key = base / "id_wrong"
        self.known_hosts = base / "known_hosts"
        self.workdir = base / "remote"
        self.sshd: subprocess.Popen | None = None
        self.made_privsep_dir = False

    def start(self) -> None:
        _sh("ip", "netns", "add", NETNS)
        _sh("ip", "link", "add", HOST_IF, "type", "veth", "peer", "name", "eth0", "netns", NETNS)
        _sh("ip", "addr", "add", f"{LOCAL_IP}/24", "dev", HOST_IF)
        _sh("ip", "link", "set", HOST_IF, "up")
        _sh("ip", "-n", NETNS, "addr", "add", f"{REMOTE_IP}/24", "dev", "eth0")
        _sh("ip", "-n", NETNS, "link", "set", "eth0", "up")
        _sh("ip", "-n", NETNS, "link", "set", "lo", "up")
        host_key = self.base / "ssh_host_ed25519_key"
        for path in (host_key, self.key, self.wrong_key):
            _sh("ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", "dvla-test", "-f", str(path))
        (self.base / "authorized_keys").write_text(self.key.with_suffix(".pub").read_text())
        host_pub = host_key.with_suffix(".pub").read_text().split()
        self.known_hosts.write_text(f"[{REMOTE_IP}]:{SSH_PORT} {host_pub[0]} {host_pub[1]}\n")
        config = self.base / "sshd_config"
        config.write_text(
            f"Port {SSH_PORT}\nListenAddress {REMOTE_IP}\nHostKey {host_key}\n"
            f"AuthorizedKeysFile {self.base / 'authorized_keys'}\nPidFile {self.base / 'sshd.pid'}\n"
            "PasswordAuthentication no\nKbdInteractiveAuthentication no\nPermitRootLogin prohibit-password\n"
            "UsePAM no\nStrictModes no\nLogLevel ERROR\n"
        )
        if not os.path.isdir("/run/sshd"):  # sshd's privilege-separation directory
            os.makedirs("/run/sshd", mode=0o755)
            self.made_privsep_dir = True
        self.sshd = subprocess.Popen(
            ["ip", "netns", "exec", NETNS, SSHD, "-D", "-e", "-f", str(config)],
            stdout=subprocess.DEVNULL, stderr=open(self.base / "sshd.log", "wb"),
        )
        _wait_port(REMOTE_IP, SSH_PORT, 10)

    def stop(self) -> None:
        if self.sshd is not None and self.sshd.poll() is None:
            self.sshd.terminate()
            try:
                self.sshd.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.sshd.kill()
                self.sshd.wait()
        left = subprocess.run(["ip", "netns", "pids", NETNS], capture_output=True, text=True).stdout.split()
        for pid in left:  # would keep the namespace alive; the test asserts there are none first
            try:
                os.kill(int(pid), signal.SIGKILL)
            except ProcessLookupError:
                pass
        subprocess.run(["ip", "netns", "del", NETNS], capture_output=True)
        subprocess.run(["ip", "link", "del", HOST_IF], capture_output=True)  # gone with the netns, normally
        if self.made_privsep_dir:
            shutil.rmtree("/run/sshd", ignore_errors=True)


@pytest.fixture(scope="module")
def remote(tmp_path_factory: pytest.TempPathFactory):
    host = RemoteHost(tmp_path_factory.mktemp("sshhost"))
    try:
        host.start()
        yield host
    finally:
        host.stop()
    assert NETNS not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert HOST_IF not in subprocess.run(["ip", "-br", "link"], capture_output=True, text=True).stdout


def _topology(tmp: Path, remote: RemoteHost, run: str, key: Path, steps: int = 600) -> Path:
    path = tmp / f"{run}.yaml"
    path.write_text(f"""
run: {run}
base_port: {free_port_block()}
task:
  env: PushCube-v1
  obs_mode: state
  envs_per_rollout: 2
  chunk_steps: 10
  ppo: {{batch_steps: 200, minibatches: 2, update_epochs: 1}}
  budget: {{max_env_steps: {steps}}}
ssh:
  port: {SSH_PORT}
  identity_file: {key}
  known_hosts_file: {remote.known_hosts}
  host_key_check: "yes"
  python: {sys.executable}
  workdir: {remote.workdir}
racks:
  - name: r0
    nodes:
      - name: here
        address: {LOCAL_IP}
        roles: [{{role: actor}}]
      - name: far
        host: {REMOTE_IP}
        roles: [{{role: rollout}}]
""")
    return path


def _processes_mentioning(text: str) -> list[str]:
    out = subprocess.run(["pgrep", "-af", "--", text], capture_output=True, text=True).stdout.splitlines()
    return [line for line in out if "pgrep" not in line and str(os.getpid()) != line.split()[0]]


@pytest.mark.timeout(240)
def test_remote_rollout_over_ssh_trains_with_local_actor(remote: RemoteHost, tmp_path: Path) -> None:
    run = f"ssh{TAG}"
    topo = _topology(tmp_path, remote, run, remote.key)
    runs = tmp_path / "runs"
    proc = subprocess.run(
        [sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs), "--quiet"],
        cwd=ROOT, capture_output=True, text=True, timeout=200,
    )
    run_dir = runs / run
    log = (run_dir / "logs" / "rollout-far-0.log").read_text(errors="replace")
    assert proc.returncode == 0, proc.stdout + proc.stderr + "\n--- remote rollout log:\n" + log[-3000:]

    # The rollout really ran on the far side of ssh: its log came back through the ssh channel,
    # its config was written on the remote side (0600), and its summary was shipped home.
    assert "ssh -T -p 2222" in log and "dvla.orchestrator.ssh serve" in log
    assert "rollout-far-0 running" in log and "stopped cleanly" in log
    remote_cfg = remote.workdir / run / "roles" / "rollout-far-0.json"
    assert stat.S_IMODE(remote_cfg.stat().st_mode) == 0o600
    assert json.loads(remote_cfg.read_text())["run_dir"] == str(remote.workdir / run)
    secret = (run_dir / "secret").read_text().strip()
    assert secret not in log  # the secret travels on stdin, never on a command line

    summary = json.loads((run_dir / "summaries" / "rollout-far-0.json").read_text())
    assert summary["extra"]["chunks_shipped"] > 0 and summary["error"] is None
    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "max_env_steps"
    acct = result["accounting"]
    # the remote rollout's counter file came back: its chunks are in the books (its status may
    # miss the last one, flushed as it closed)
    assert acct["incarnations"] == {"rollout": 1, "actor": 1}
    assert 0 <= acct["produced"] - summary["extra"]["chunks_shipped"] <= 1
    assert acct["consumed"] > 0 and acct["unaccounted"] == 0, acct

    assert not (run_dir / "state.json").exists()
    assert _processes_mentioning(str(remote.workdir)) == []
    assert _processes_mentioning(str(run_dir)) == []


def _up_fails_with_one_line(topo: Path, tmp_path: Path) -> str:
    """`dvla up topo` exits 2 before starting anything, with exactly one `dvla:` error line."""
    proc = subprocess.run(
        [sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(tmp_path / "runs"), "--quiet"],
        cwd=ROOT, capture_output=True, text=True, timeout=50,
    )
    assert proc.returncode == 2, proc.stdout + proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("dvla:")]
    assert len(errors) == 1, proc.stderr
    return errors[0]


@pytest.mark.timeout(60)
def test_failed_login_is_one_line_naming_the_host(remote: RemoteHost, tmp_path: Path) -> None:
    run = f"sshbad{TAG}"
    error = _up_fails_with_one_line(_topology(tmp_path, remote, run, remote.wrong_key), tmp_path)
    assert f"ssh {REMOTE_IP}:{SSH_PORT} failed" in error and "Permission denied" in error, error
    assert _processes_mentioning(str(tmp_path)) == []


@pytest.mark.timeout(60)
def test_foreign_remote_run_directory_is_left_alone(remote: RemoteHost, tmp_path: Path) -> None:
    """A directory at <workdir>/<run> without dvla's token file is someone else's: `dvla up` stops
    before anything starts, with one line naming host and path, and the directory survives."""
    run = f"sshforeign{TAG}"
    foreign = remote.workdir / run
    foreign.mkdir(parents=True)
    (foreign / "notes.txt").write_text("not dvla's")
    error = _up_fails_with_one_line(_topology(tmp_path, remote, run, remote.key), tmp_path)
    assert f"ssh {REMOTE_IP}:{SSH_PORT}: " in error and f"{foreign} exists and is not a dvla run directory" in error
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]
    assert not (tmp_path / "runs" / run / "logs" / "rollout-far-0.log").exists()  # nothing started


@pytest.mark.timeout(120)
def test_killed_orchestrator_leaves_nothing_on_the_remote_side(remote: RemoteHost, tmp_path: Path) -> None:
    run = f"sshkill{TAG}"
    topo = _topology(tmp_path, remote, run, remote.key, steps=1_000_000)
    runs = tmp_path / "runs"
    up = subprocess.Popen(
        [sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs), "--quiet"],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    remote_cfg = str(remote.workdir / run / "roles")
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not _processes_mentioning(f"--config {remote_cfg}"):
            assert up.poll() is None, "dvla up exited early"
            time.sleep(0.2)
        assert _processes_mentioning(f"--config {remote_cfg}"), "the remote role never started"
    finally:
        up.kill()  # SIGKILL: no clean-up code of the orchestrator runs
        up.wait()
    # ssh dies with the orchestrator (parent-death signal); sshd closes the remote command's
    # stdin; the remote side kills the role.
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and _processes_mentioning(str(remote.workdir / run)):
        time.sleep(0.2)
    assert _processes_mentioning(str(remote.workdir / run)) == []
    assert _processes_mentioning(str(runs / run)) == []
    sessions = subprocess.run(["ip", "netns", "pids", NETNS], capture_output=True, text=True).stdout.split()
    assert sessions == [str(remote.sshd.pid)], sessions  # only the listening sshd

"""W&B (`logging.wandb`) on real `dvla up` runs of the tiny topology, with no network.

Each run happens inside a network namespace whose only way out is a black hole: a veth into a
second, empty namespace that never answers, the default route through it, and a resolv.conf
naming a name server behind it (``ip netns exec`` mounts /etc/netns/<ns>/resolv.conf). So a
name lookup or a connection hangs as on a dead network instead of failing at once, and every
packet that tries to leave is counted on the veth.

- offline: the run ends normally; its W&B files under runs/<run>/wandb hold the same scalars as
  its TensorBoard files, by env steps, and the task as W&B config; not one packet left the
  namespace; no W&B service process is left.
- online: W&B cannot reach its server (it tried: packets were counted); the run still ends
  normally, with one warning line naming `logging.wandb`, and no W&B service process is left.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from .test_up_e2e import free_port_block, pids_of_run

ROOT = Path(__file__).resolve().parents[2]
TAG = os.getpid() % 100000
NETNS = f"dvwb{TAG}"
VOID = f"dvwb{TAG}v"
#: TEST-NET-1 (RFC 5737): nothing answers there
DEAD_NAMESERVER = "192.0.2.53"
STEPS = 800


def _usable() -> tuple[bool, str]:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        return False, "needs root and `ip`"
    if subprocess.run(["ip", "netns", "list"], capture_output=True).returncode != 0:
        return False, "needs `ip netns`"
    try:
        import wandb  # noqa: F401
    except ImportError:
        return False, "needs wandb (pip install 'dvla[wandb]')"
    return True, ""


_OK, _WHY = _usable()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(not _OK, reason=_WHY)]


def _sh(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=30)


class BlackHole:
    """A namespace with loopback and a default route into nothing, counting what goes out."""

    etc = Path("/etc/netns") / NETNS

    def start(self) -> None:
        _sh("ip", "netns", "add", NETNS)
        _sh("ip", "netns", "add", VOID)
        _sh("ip", "-n", NETNS, "link", "set", "lo", "up")
        # no IPv6: router and neighbour solicitations would be counted as traffic
        _sh("ip", "netns", "exec", NETNS, "sysctl", "-qw", "net.ipv6.conf.all.disable_ipv6=1",
            "net.ipv6.conf.default.disable_ipv6=1")
        _sh("ip", "-n", NETNS, "link", "add", "out0", "type", "veth", "peer", "name", "in0", "netns", VOID)
        _sh("ip", "-n", NETNS, "link", "set", "out0", "arp", "off")  # packets go out, no ARP first
        _sh("ip", "-n", NETNS, "link", "set", "out0", "up")
        _sh("ip", "-n", VOID, "link", "set", "in0", "up")
        _sh("ip", "-n", NETNS, "route", "add", "default", "dev", "out0")
        self.etc.mkdir(parents=True, exist_ok=True)
        (self.etc / "resolv.conf").write_text(f"nameserver {DEAD_NAMESERVER}\n")

    def sent_packets(self) -> int:
        out = subprocess.run(["ip", "netns", "exec", NETNS, "cat", "/sys/class/net/out0/statistics/tx_packets"],
                             capture_output=True, text=True, check=True).stdout
        return int(out)

    def stop(self) -> None:
        for ns in (NETNS, VOID):
            left = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True).stdout.split()
            for pid in left:  # would keep the namespace alive
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except ProcessLookupError:
                    pass
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        shutil.rmtree(self.etc, ignore_errors=True)


@pytest.fixture(scope="module")
def black_hole():
    hole = BlackHole()
    try:
        hole.start()
        yield hole
    finally:
        hole.stop()
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout.split()
    assert NETNS not in listed and VOID not in listed and not BlackHole.etc.exists()


def _up_in(hole: BlackHole, tmp_path: Path, wandb: str, steps: int,
           env: dict[str, str] | None = None) -> tuple[subprocess.Popen, str, Path]:
    """`dvla up` of tiny.yaml plus `logging: {wandb: <wandb>}` inside the namespace: (process, output, run dir)."""
    topo = tmp_path / "tiny-wandb.yaml"
    topo.write_text((ROOT / "topologies" / "tiny.yaml").read_text() + f"\nlogging:\n  wandb: {wandb}\n")
    runs = tmp_path / "runs"
    full_env = {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")}
    full_env.update(env or {})
    up = subprocess.Popen(
        ["ip", "netns", "exec", NETNS, sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs),
         "--base-port", str(free_port_block()), "--max-env-steps", str(steps), "--quiet"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=full_env,
    )
    try:
        out, _ = up.communicate(timeout=240)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    return up, out, runs / "tiny"


def _wandb_services_of(pid: int) -> list[str]:
    """W&B service processes started by process `pid` (wandb-core watches its parent with --pid)."""
    out = subprocess.run(["pgrep", "-af", "wandb-core"], capture_output=True, text=True).stdout.splitlines()
    return [line for line in out if f"--pid {pid}" in line]


@pytest.mark.timeout(300)
def test_offline_run_writes_the_tensorboard_scalars_and_touches_no_network(black_hole: BlackHole, tmp_path: Path) -> None:
    sent_before = black_hole.sent_packets()
    up, out, run_dir = _up_in(black_hole, tmp_path, "{project: dvla-test, mode: offline}", STEPS)
    assert up.returncode == 0, out
    assert black_hole.sent_packets() == sent_before, "an offline run sent packets out of its namespace"
    assert _wandb_services_of(up.pid) == [] and pids_of_run(run_dir) == []

    offline = sorted((run_dir / "wandb").glob("offline-run-*"))
    assert len(offline) == 1, offline
    assert f"wandb sync {run_dir / 'wandb'}/offline-run-*" in out  # printed beside the TensorBoard line
    assert f"wandb: offline run in {offline[0]}; upload it with: wandb sync {offline[0]}" in out
    assert "warning: logging.wandb" not in out

    records = read_wandb_file(next(offline[0].glob("run-*.wandb")))
    history = [r for kind, r in records if kind == "history"]
    assert history and any(kind == "exit" for kind, _ in records)  # wandb.finish() ran
    config = next(r for kind, r in records if kind == "config")
    assert config["task"]["env"] == "PushCube-v1" and config["task"]["ppo"]["batch_steps"] == 400

    # the same scalars as TensorBoard, by env steps
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tb = EventAccumulator(str(run_dir / "tb"))
    tb.Reload()
    tb_tags = set(tb.Tags()["scalars"])
    wandb_tags = {k for row in history for k in row if not k.startswith("_") and k != "env_steps"}
    assert wandb_tags == tb_tags, (wandb_tags ^ tb_tags)
    assert {"train/approx_kl", "env/success_rate", "weights/version", "time/actor.learn/busy"} <= wandb_tags
    tb_versions = [(e.step, e.value) for e in tb.Scalars("weights/version")]
    wandb_versions = [(row["env_steps"], row["weights/version"]) for row in history if "weights/version" in row]
    assert wandb_versions == tb_versions
    steps = [row["env_steps"] for row in history]
    assert steps == sorted(steps) and steps[-1] >= STEPS


@pytest.mark.timeout(300)
def test_online_without_network_warns_once_and_the_run_goes_on(black_hole: BlackHole, tmp_path: Path) -> None:
    sent_before = black_hole.sent_packets()
    up, out, run_dir = _up_in(
        black_hole, tmp_path, "{project: dvla-test, mode: online, init_timeout_s: 3, finish_timeout_s: 5}", STEPS // 2,
        # a key of the right shape: W&B then reaches for its server rather than refusing at once
        env={"WANDB_API_KEY": "0123456789abcdef" * 2 + "01234567"},
    )
    assert up.returncode == 0, out
    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "max_env_steps" and result["final_env_steps"] >= STEPS // 2
    warnings = [line for line in out.splitlines() if "logging.wandb" in line]
    assert len(warnings) == 1 and "warning: logging.wandb: W&B online run did not start" in warnings[0], out
    assert "the run goes on without W&B" in warnings[0]
    assert black_hole.sent_packets() > sent_before, "W&B never tried the network: the black hole saw nothing"
    assert _wandb_services_of(up.pid) == [] and pids_of_run(run_dir) == []
    assert (run_dir / "tb").is_dir() and any((run_dir / "tb").iterdir())


# ------------------------------------------------------------------------------------------
# reading a .wandb file


#: a .wandb file is a LevelDB-format log: a 7-byte file header, then 32 KiB blocks of records,
#: each with a 7-byte header (CRC32, length, type) and a wandb_internal.proto Record as payload
BLOCK = 32 * 1024
HEADER = 7
FULL, FIRST, MIDDLE, LAST = 1, 2, 3, 4


def read_wandb_file(path: Path) -> list[tuple[str, dict]]:
    """(record kind, its content) of every record of a .wandb file; history rows, the config and
    summaries as plain dicts (W&B's protobuf schema, the file format written out here: recent
    wandb versions have no reader of their own)."""
    from wandb.proto import wandb_internal_pb2 as pb

    data = path.read_bytes()
    assert data[:4] == b":W&B", data[:HEADER]
    out: list[tuple[str, dict]] = []
    pos, pending = HEADER, b""
    while pos + HEADER <= len(data):
        left = BLOCK - pos % BLOCK
        if left < HEADER:  # a block's tail too short for a record header is padding
            pos += left
            continue
        _crc, length, kind = struct.unpack("<IHB", data[pos:pos + HEADER])
        body = data[pos + HEADER:pos + HEADER + length]
        pos += HEADER + length
        if kind in (FIRST, MIDDLE):
            pending += body
            continue
        if kind not in (FULL, LAST):
            continue
        record = pb.Record()
        record.ParseFromString(pending + body)
        pending = b""
        which = record.WhichOneof("record_type")
        if which == "history":
            out.append(("history", _items(record.history.item)))
        elif which == "run":
            out.append(("config", _items(record.run.config.update)))
        else:
            out.append((which, {}))
    return out


def _items(items) -> dict:
    return {(i.key or "/".join(i.nested_key)): json.loads(i.value_json) for i in items}

"""What a remote role (over SSH or as a Slurm step) sends back, and what is sent to it. A remote
rank-0 actor's checkpoint travels: back with its results (into the local run directory, where
`dvla up --resume` and `dvla export` read it) and, when a continued run starts it on a node, out
to that node after the stdin header; never backwards, never anything else. Counter files of a
killed incarnation come back with the next one."""

from __future__ import annotations

import io
import json
import tarfile
from pathlib import Path

import pytest

from dvla.orchestrator.plan import make_plan
from dvla.orchestrator.ssh import (SshWrapper, checkpoint_tar, result_path_problem, unpack_checkpoint,
                                   unpack_results, writes_checkpoints, _results_tar)
from dvla.orchestrator.topology import parse_topology


def write_checkpoint(run_dir: Path, version: int, high_water: int, payload: bytes = b"w") -> None:
    d = run_dir / "checkpoints"
    (d / f"v{version:08d}").mkdir(parents=True, exist_ok=True)
    for f in ("policy.safetensors", "optimizer.safetensors"):
        (d / f"v{version:08d}" / f).write_bytes(payload)
    (d / "high_water.json").write_text(json.dumps({"version": high_water}))
    (d / "MANIFEST.json").write_text(json.dumps({"format": 1, "version": version, "dir": f"v{version:08d}"}))


def version_of(run_dir: Path) -> tuple[int, int]:
    d = run_dir / "checkpoints"
    return (json.loads((d / "MANIFEST.json").read_text())["version"],
            json.loads((d / "high_water.json").read_text())["version"])


def test_a_rank0_actor_sends_its_current_checkpoint_back(tmp_path: Path) -> None:
    remote = tmp_path / "remote"
    write_checkpoint(remote, 7, 16)
    (remote / "checkpoints" / "v00000003").mkdir()  # an older one stays where it is
    (remote / "checkpoints" / "v00000003" / "policy.safetensors").write_bytes(b"old")
    data = _results_tar(remote, "actor-far-0", since=0.0, checkpoints=True)
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        assert tar.getnames() == ["checkpoints/v00000007/policy.safetensors", "checkpoints/v00000007/optimizer.safetensors",
                                  "checkpoints/high_water.json", "checkpoints/MANIFEST.json"]  # the manifest last
    tar_path = tmp_path / "r.tar"
    tar_path.write_bytes(data)
    local = tmp_path / "local"
    assert len(unpack_results(tar_path, local, "actor-far-0", checkpoints=True)) == 4
    assert version_of(local) == (7, 16)
    # any other role sending a checkpoint is refused whole
    tar_path.write_bytes(data)
    with pytest.raises(Exception, match="refused, nothing unpacked: 'checkpoints/v00000007/policy.safetensors'"):
        unpack_results(tar_path, tmp_path / "other", "rollout-far-0")
    member = tarfile.TarInfo("checkpoints/optimizer.pt")
    assert result_path_problem(member, "actor-far-0", checkpoints=True) is not None


TOPO = """
run: r
racks:
  - name: r0
    nodes:
      - {name: here, host: localhost, address: 10.0.0.1, roles: [{role: replicator}, {role: evaluator}]}
      - {name: far, host: gpu-7, roles: [{role: actor}, {role: rollout}]}
"""


def test_a_continued_run_sends_the_checkpoint_to_its_remote_rank0(tmp_path: Path) -> None:
    topo = parse_topology(TOPO, "t.yaml")
    plan = make_plan(topo, str(tmp_path / "run"))
    wrapper = SshWrapper(topo, "ab" * 32, {})
    actor, rollout = plan.by_name("actor-far-0"), plan.by_name("rollout-far-0")
    assert writes_checkpoints(actor.config) and not writes_checkpoints(rollout.config)
    argv = ["python", "-m", "dvla.roles.actor", "--config", "x"]
    # nothing to continue from: the header alone
    assert json.loads(wrapper.stdin_payload(actor, argv))["checkpoint_bytes"] == 0
    write_checkpoint(tmp_path / "run", 5, 16)
    payload = wrapper.stdin_payload(actor, argv)
    head, _, attached = payload.partition(b"\n")
    assert json.loads(head)["checkpoint_bytes"] == len(attached) == len(checkpoint_tar(tmp_path / "run")) > 0
    assert json.loads(wrapper.stdin_payload(rollout, argv).partition(b"\n")[0])["checkpoint_bytes"] == 0
    # the node writes it, unless what it holds is as new; the high-water mark never goes down
    node = tmp_path / "node"
    assert unpack_checkpoint(attached, node) and version_of(node) == (5, 16)
    write_checkpoint(node, 6, 32)
    assert not unpack_checkpoint(attached, node) and version_of(node) == (6, 32)
    write_checkpoint(node, 4, 48)
    assert unpack_checkpoint(attached, node) and version_of(node) == (5, 48)


def test_a_checkpoint_tar_holding_anything_else_is_refused(tmp_path: Path) -> None:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        info = tarfile.TarInfo("checkpoints/../../etc/x")
        info.size = 1
        tar.addfile(info, io.BytesIO(b"x"))
    with pytest.raises(ValueError, match="is not a checkpoint file"):
        unpack_checkpoint(buf.getvalue(), tmp_path)
    assert not any(tmp_path.iterdir())


def test_counters_of_an_incarnation_killed_with_its_step_come_back_with_the_next(tmp_path: Path) -> None:
    import os

    remote = tmp_path / "remote"
    for rel in ("counters/rollout-far-0.0.111", "counters/rollout-far-0.1.222", "summaries/rollout-far-0.json"):
        (remote / rel).parent.mkdir(parents=True, exist_ok=True)
        (remote / rel).write_text("x")
        os.utime(remote / rel, (1000.0, 1000.0))  # written before this incarnation started
    with tarfile.open(fileobj=io.BytesIO(_results_tar(remote, "rollout-far-0", since=2000.0))) as tar:
        assert sorted(tar.getnames()) == ["counters/rollout-far-0.0.111", "counters/rollout-far-0.1.222"]

"""dvla.orchestrator.ssh against hostile input, without a remote host: the ssh command line
(host after ``--``), result tars from remote nodes (only the role's own result files), and the
remote run directory (only dvla's own is ever deleted). See docs/security.md."""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from dvla.config import SshConfig
from dvla.orchestrator.ssh import (
    NOT_OURS,
    TOKEN_FILE,
    ResultsRefused,
    RunDirError,
    SshTarget,
    _results_tar,
    prepare_run_dir,
    run_dir_action,
    unpack_results,
)

ROOT = Path(__file__).resolve().parents[2]
ROLE = "rollout-far-0"

# ------------------------------------------------------------------------------------------
# the ssh command line


def test_destination_comes_after_the_option_terminator() -> None:
    target = SshTarget("-oProxyCommand=touch pwned", SshConfig(user="rl", identity_file="/k"))
    argv = target.argv("python3 -m dvla.orchestrator.ssh serve")
    end = argv.index("--")
    assert argv[end + 1:] == ["rl@-oProxyCommand=touch pwned", "python3 -m dvla.orchestrator.ssh serve"]
    assert all(not a.startswith("-oProxy") for a in argv[:end])
    assert argv[:4] == ["ssh", "-T", "-p", "22"]


def test_bracketed_ipv6_host_is_given_to_ssh_bare() -> None:
    assert SshTarget("[fe80::1%eth0]", SshConfig()).destination == "fe80::1%eth0"
    assert SshTarget("[::1]", SshConfig(user="rl")).destination == "rl@::1"
    assert SshTarget("[::1]", SshConfig(port=2222)).label() == "[::1]:2222"


@pytest.mark.skipif(shutil.which("ssh") is None, reason="needs the OpenSSH client")
def test_real_ssh_client_never_runs_a_host_as_an_option(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    target = SshTarget(f"-oProxyCommand=touch {marker}", SshConfig(connect_timeout_s=2, known_hosts_file=os.devnull))
    proc = subprocess.run(target.argv("true"), capture_output=True, text=True, timeout=30, stdin=subprocess.DEVNULL)
    assert proc.returncode == 255 and not marker.exists(), proc.stderr
    # the same host before the option terminator is what the fix prevents
    unsafe = subprocess.run(["ssh", "-G", f"-oProxyCommand=touch {marker}", "x"], capture_output=True, text=True, timeout=30)
    assert f"proxycommand touch {marker}" in unsafe.stdout.lower()


# ------------------------------------------------------------------------------------------
# result tars


def _tar(path: Path, members: list[tuple[str, bytes | None, bytes]]) -> Path:
    """members: (name, tar type or None for a regular file, content or link target)."""
    with tarfile.open(path, "w") as tar:
        for name, kind, data in members:
            info = tarfile.TarInfo(name)
            if kind is None:
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
            else:
                info.type = kind
                info.linkname = data.decode()
                tar.addfile(info)
    return path


GOOD = [(f"summaries/{ROLE}.json", None, b"{}"), (f"counters/{ROLE}.0.4242", None, b'{"produced": 3}')]


def test_good_results_unpack(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    tar = _tar(tmp_path / "r.tar", GOOD)
    assert unpack_results(tar, run_dir, ROLE, "rl@gpu:22") == [f"summaries/{ROLE}.json", f"counters/{ROLE}.0.4242"]
    assert (run_dir / "counters" / f"{ROLE}.0.4242").read_bytes() == b'{"produced": 3}'
    assert not tar.exists()


def test_actor_may_send_its_version_ledger(tmp_path: Path) -> None:
    tar = _tar(tmp_path / "r.tar", [("versions.csv", None, b"version,t\n")])
    assert unpack_results(tar, tmp_path / "run", "actor-far-0") == ["versions.csv"]
    tar = _tar(tmp_path / "r.tar", [("versions.csv", None, b"version,t\n")])
    with pytest.raises(ResultsRefused):
        unpack_results(tar, tmp_path / "run", ROLE)


BAD = {
    "optimizer checkpoint": ("checkpoints/optimizer.pt", None, b"\x80\x04evil"),
    "manifest": ("checkpoints/MANIFEST.json", None, b"{}"),
    "role config": ("roles/x.json", None, b"{}"),
    "topology": ("topology.yaml", None, b"run: x"),
    "state": ("state.json", None, b"{}"),
    "secret": ("secret", None, b"00"),
    "cache": ("cache/torchinductor/x.py", None, b"import os"),
    "dotdot": ("../x", None, b"x"),
    "dotdot inside": (f"summaries/../../{ROLE}.json", None, b"x"),
    "absolute": (f"/tmp/{ROLE}.json", None, b"x"),
    "symlink": (f"summaries/{ROLE}.json", tarfile.SYMTYPE, b"/etc/passwd"),
    "hard link": (f"summaries/{ROLE}.json", tarfile.LNKTYPE, b"secret"),
    "device": (f"summaries/{ROLE}.json", tarfile.CHRTYPE, b""),
    "fifo": (f"summaries/{ROLE}.json", tarfile.FIFOTYPE, b""),
    "directory": ("summaries", tarfile.DIRTYPE, b""),
    "another role's summary": ("summaries/actor-here-0.json", None, b"{}"),
    "prefix of another role": (f"summaries/{ROLE}.x-0.json", None, b"{}"),
    "nested": (f"summaries/sub/{ROLE}.json", None, b"{}"),
    "hidden": (f"summaries/.{ROLE}.json", None, b"{}"),
}


@pytest.mark.parametrize("what", sorted(BAD))
def test_unexpected_member_refuses_the_whole_tar(tmp_path: Path, what: str) -> None:
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    name = BAD[what][0]
    tar = _tar(tmp_path / "r.tar", [*GOOD, BAD[what]])
    with pytest.raises(ResultsRefused) as info:
        unpack_results(tar, run_dir, ROLE, "rl@gpu-7:22")
    message = str(info.value)
    assert "\n" not in message and "rl@gpu-7:22" in message and repr(name) in message and "nothing unpacked" in message
    assert list(run_dir.iterdir()) == []  # not even the good members
    assert not (tmp_path / "x").exists() and not tar.exists()


def test_refusal_is_reported_as_an_event_by_the_wrapper(tmp_path: Path) -> None:
    """SshWrapper.finished turns a refused tar into one event line naming the role and host."""
    from types import SimpleNamespace

    from dvla.orchestrator.ssh import SshWrapper

    run_dir = tmp_path / "run"
    (run_dir / "logs").mkdir(parents=True)
    (run_dir / "remote").mkdir()
    _tar(run_dir / "remote" / f"{ROLE}.tar", [("checkpoints/optimizer.pt", None, b"\x80")])
    wrapper = SshWrapper.__new__(SshWrapper)
    wrapper.targets = {"far": SshTarget("gpu-7", SshConfig(user="rl"))}
    sup = SimpleNamespace(name=ROLE, proc=SimpleNamespace(config=SimpleNamespace(node="far")),
                          log_path=run_dir / "logs" / f"{ROLE}.log")
    note = wrapper.finished(sup, 0)  # type: ignore[arg-type]
    assert note == (f"{ROLE}: results from rl@gpu-7:22 refused, nothing unpacked: 'checkpoints/optimizer.pt' is not a"
                    f" result file of {ROLE} (expected summaries/{ROLE}.*, counters/{ROLE}.*, or an actor's versions.csv)")
    assert not (run_dir / "checkpoints").exists()


def test_remote_side_sends_only_what_the_local_side_accepts(tmp_path: Path) -> None:
    run_dir = tmp_path / "remote"
    for rel in (f"summaries/{ROLE}.json", f"counters/{ROLE}.0.77", "summaries/other-0.json", "checkpoints/v00000001/x",
                f"roles/{ROLE}.json", "cache/torchinductor/k.py", "versions.csv", TOKEN_FILE, f"summaries/{ROLE}.tmp"):
        (run_dir / rel).parent.mkdir(parents=True, exist_ok=True)
        (run_dir / rel).write_text("x")
    (run_dir / "summaries" / f"{ROLE}.json.lnk").symlink_to("/etc/passwd")
    data = _results_tar(run_dir, ROLE, since=0.0)
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        assert sorted(tar.getnames()) == [f"counters/{ROLE}.0.77", f"summaries/{ROLE}.json"]
    path = tmp_path / "r.tar"
    path.write_bytes(data)
    assert len(unpack_results(path, tmp_path / "local", ROLE)) == 2


# ------------------------------------------------------------------------------------------
# remote run directories


def test_run_dir_decisions(tmp_path: Path) -> None:
    d = tmp_path / "run"
    assert run_dir_action(d, "t1")[0] == "create"
    d.mkdir()
    assert run_dir_action(d, "t1") == ("refuse", f"exists and is not a dvla run directory (no {TOKEN_FILE})")
    (d / "data.bin").write_text("precious")
    assert run_dir_action(d, "t1")[0] == "refuse"
    (d / TOKEN_FILE).write_text("t0\n")
    assert run_dir_action(d, "t1")[0] == "wipe"
    assert run_dir_action(d, "t0")[0] == "keep"
    (d / TOKEN_FILE).unlink()
    (d / TOKEN_FILE).symlink_to(tmp_path / "elsewhere")
    assert run_dir_action(d, "t1")[0] == "refuse"
    link = tmp_path / "link"
    link.symlink_to(d)
    assert run_dir_action(link, "t1")[0] == "refuse"
    f = tmp_path / "file"
    f.write_text("x")
    assert run_dir_action(f, "t1")[0] == "refuse"


def test_prepare_creates_wipes_its_own_and_keeps_restarts(tmp_path: Path) -> None:
    d = tmp_path / "work" / "run"
    prepare_run_dir(d, "t1")
    assert (d / TOKEN_FILE).read_text() == "t1\n"
    (d / "checkpoints").mkdir()
    prepare_run_dir(d, "t1")  # a restart of the same run keeps its files
    assert (d / "checkpoints").exists()
    prepare_run_dir(d, "t2")  # an earlier run's directory (dvla's own) is emptied
    assert sorted(p.name for p in d.iterdir()) == [TOKEN_FILE]


def test_prepare_leaves_a_foreign_directory_alone(tmp_path: Path) -> None:
    d = tmp_path / "run"
    d.mkdir()
    (d / "thesis.tex").write_text("years of work")
    with pytest.raises(RunDirError) as info:
        prepare_run_dir(d, "t1")
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{os.uname().nodename}: {d} exists and is not a dvla run directory")
    assert (d / "thesis.tex").read_text() == "years of work" and not (d / TOKEN_FILE).exists()


def _remote_module(arg: str, header: dict | None, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "dvla.orchestrator.ssh", arg], input=json.dumps(header) + "\n" if header else "",
                          capture_output=True, text=True, timeout=60, env=env, cwd=cwd)


def test_remote_probe_and_serve_refuse_a_foreign_run_directory(tmp_path: Path) -> None:
    """The remote half run directly: `probe` (before anything starts) and `serve` both stop with
    one line naming host and path, and the directory survives."""
    d = tmp_path / "work" / "run"
    d.mkdir(parents=True)
    (d / "keep.txt").write_text("mine")
    probe = _remote_module("probe", {"run_dir": str(d), "token": "t1"}, tmp_path)
    assert probe.returncode == NOT_OURS and probe.stdout == ""
    assert probe.stderr.strip() == (f"{os.uname().nodename}: {d} exists and is not a dvla run directory (no {TOKEN_FILE});"
                                    " left as it is: move it away or set ssh.workdir to another directory")
    serve = _remote_module("serve", {"run_dir": str(d), "token": "t1", "config": {"name": ROLE}}, tmp_path)
    assert serve.returncode == NOT_OURS and serve.stderr.strip().startswith(f"dvla ssh serve: {os.uname().nodename}: {d}")
    assert serve.stdout == ""
    assert sorted(p.name for p in d.iterdir()) == ["keep.txt"]
    # a probe without a header (dvla doctor) prepares nothing; with one on a fresh path, it creates it
    assert json.loads(_remote_module("probe", None, tmp_path).stdout)["python"]
    fresh = tmp_path / "work" / "run2"
    assert _remote_module("probe", {"run_dir": str(fresh), "token": "t9"}, tmp_path).returncode == 0
    assert (fresh / TOKEN_FILE).read_text() == "t9\n"

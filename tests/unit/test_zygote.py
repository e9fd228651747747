"""Warm role starts (dvla/orchestrator/zygote.py) with real processes: a role forked by the zygote
runs as `python -m <module>` would (its argv, its environment, a session of its own, stdin from
/dev/null, output in its log, the command line `ps` shows), is supervised as a Popen is (exit
codes, signals, wait timeouts), and dies with the zygote; a zygote whose imports start a thread
refuses to fork and says why."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from dvla.orchestrator.zygote import Zygote

ROOT = Path(__file__).resolve().parents[2]
MODULE = "tests.zygote_probe.probe"


@pytest.fixture
def env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def _wait_file(path: Path, timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            time.sleep(0.05)
    raise AssertionError(f"{path} never written")


def test_a_forked_role_runs_as_python_m_would_and_reports_its_exit(tmp_path: Path, env: dict[str, str]) -> None:
    zyg = Zygote(["json"], env, tmp_path, tmp_path / "zygote.log")
    try:
        assert zyg.wait_ready(), zyg.why_not
        out, log = tmp_path / "probe.json", tmp_path / "probe.log"
        role = zyg.spawn(MODULE, [str(out), "7"], {**env, "PROBE_VALUE": "forked"}, log)
        assert role is not None and role.stdin is None
        assert role.wait(timeout=60) == 7 and role.poll() == 7
        doc = json.loads(out.read_text())
        assert doc["argv"] == [str(out), "7"] and doc["env"] == "forked" and doc["name"] == "__main__"
        assert doc["pid"] == role.pid == doc["pgid"] == doc["sid"]  # leads a session of its own
        assert doc["stdin"] == ""  # /dev/null
        assert f"-m {MODULE} {out} 7" in doc["cmdline"]  # as ps and pgrep -f see it
        assert f"probe {role.pid} says hello" in log.read_text()
    finally:
        zyg.close()
    assert zyg.proc.returncode == 0


def test_signals_wait_timeouts_and_death_with_the_zygote(tmp_path: Path, env: dict[str, str]) -> None:
    zyg = Zygote([], env, tmp_path, tmp_path / "zygote.log")
    assert zyg.wait_ready(), zyg.why_not
    try:
        first = zyg.spawn(MODULE, [str(tmp_path / "a.json"), "-1"], env, tmp_path / "a.log")
        assert first is not None
        _wait_file(tmp_path / "a.json")
        with pytest.raises(subprocess.TimeoutExpired):
            first.wait(timeout=0.2)
        os.killpg(first.pid, signal.SIGTERM)  # the launcher signals a role's process group
        assert first.wait(timeout=60) == -signal.SIGTERM
        second = zyg.spawn(MODULE, [str(tmp_path / "b.json"), "-1"], env, tmp_path / "b.log")
        assert second is not None
        _wait_file(tmp_path / "b.json")
    finally:
        zyg.close()  # the zygote exits; its child dies with it (PR_SET_PDEATHSIG)
    deadline = time.monotonic() + 30
    while Path(f"/proc/{second.pid}").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not Path(f"/proc/{second.pid}").exists()


def test_a_zygote_whose_imports_start_a_thread_does_not_fork(tmp_path: Path, env: dict[str, str]) -> None:
    zyg = Zygote(["tests.zygote_probe.threaded"], env, tmp_path, tmp_path / "zygote.log")
    try:
        assert not zyg.wait_ready()
        assert "2 threads after importing tests.zygote_probe.threaded" in zyg.why_not
        assert zyg.spawn(MODULE, [str(tmp_path / "c.json"), "0"], env, tmp_path / "c.log") is None
    finally:
        zyg.close()

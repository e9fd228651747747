"""`dvla up --detach`: returns at once with the run in the background; `dvla status` sees it from
another process; `dvla down` stops it cleanly; nothing of the run is left."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

from .test_up_e2e import ROOT, dvla, free_port_block, pids_of_run


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[-1].split()[0] != "Z"


@pytest.mark.timeout(300)
def test_detach_status_down(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    run_dir = runs / "tiny"
    # tiny, down to one actor and one rollout: the fewest processes a run can have
    topo = tmp_path / "tiny.yaml"
    text = (ROOT / "topologies" / "tiny.yaml").read_text()
    roles = text[text.index("        roles:"):]
    topo.write_text(text.replace(roles, "        roles: [{role: actor}, {role: rollout}]\n"))
    up = dvla("up", str(topo), "--runs", str(runs), "--base-port", str(free_port_block()),
              "--max-env-steps", "1000000", "--detach", timeout=200)
    pid = None
    try:
        assert up.returncode == 0, up.stdout + up.stderr
        assert str(run_dir) in up.stdout
        for hint in ("dvla status tiny", "dvla logs", "dvla down tiny"):
            assert hint in up.stdout, up.stdout
        state = json.loads((run_dir / "state.json").read_text())
        pid = int(state["pid"])
        # back as soon as the roles are started, not at the end: the run goes on, a daemon in its
        # own session (no terminal's Ctrl-C or hang-up reaches it), not its leader
        assert _alive(pid) and os.getsid(pid) != os.getsid(0) and os.getsid(pid) != pid

        names: set[str] = set()
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(names) < 2:
            st = dvla("status", "tiny", "--runs", str(runs), "--format", "json", timeout=60)
            if st.returncode == 0:
                names = {r["name"] for r in json.loads(st.stdout)["roles"]}
            time.sleep(1)
        assert names == {"actor-node0-0", "rollout-node0-0"}

        down = dvla("down", "tiny", "--runs", str(runs), "--timeout", "120", timeout=180)
        assert down.returncode == 0, down.stdout + down.stderr
        assert "did not stop" not in down.stderr  # stopped by its own shutdown, not killed
    finally:
        if pid is not None and _alive(pid):
            os.kill(pid, 9)
    assert not _alive(pid)
    log = (run_dir / "orchestrator.log").read_text()
    assert "ended: interrupted" in log, log[-2000:]
    assert json.loads((run_dir / "result.json").read_text())["reason"] == "interrupted"
    assert not (run_dir / "state.json").exists()
    assert pids_of_run(run_dir) == []

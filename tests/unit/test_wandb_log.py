"""`logging.wandb`: its topology keys and their one-line errors, the missing-package error of
`dvla up`, and the W&B thread's promises (dvla.orchestrator.wandb_log) against a stand-in wandb
module: the monitor never waits, a full queue drops and counts, a failed init is one warning, the
end of a run is bounded."""

from __future__ import annotations

import importlib.util
import sys
import threading
import time
import types
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from dvla.config import WandbConfig
from dvla.orchestrator import wandb_log
from dvla.orchestrator.cli import app
from dvla.orchestrator.topology import TopologyError, dump_topology_yaml, parse_topology
from dvla.orchestrator.wandb_log import WandbLog, missing_wandb, open_hint

ROOT = Path(__file__).resolve().parents[2]
TINY = (ROOT / "topologies" / "tiny.yaml").read_text()


def _with_logging(section: str) -> str:
    return TINY + f"\nlogging:\n{section}\n"


def _problems(text: str) -> list[str]:
    with pytest.raises(TopologyError) as info:
        parse_topology(text, "tiny.yaml")
    return [str(p) for p in info.value.problems]


# ------------------------------------------------------------------------------------------
# topology keys


def test_wandb_is_off_by_default() -> None:
    assert parse_topology(TINY, "tiny.yaml").logging.wandb is None


def test_wandb_section_is_read_with_its_defaults() -> None:
    topo = parse_topology(_with_logging("  wandb: {project: my-project, mode: online, entity: team, tags: [a, b]}"))
    assert topo.logging.wandb == WandbConfig(project="my-project", mode="online", entity="team", tags=("a", "b"))
    offline = parse_topology(_with_logging("  wandb: {project: p}")).logging.wandb
    assert offline == WandbConfig(project="p")
    assert offline.mode == "offline" and offline.name is None and offline.init_timeout_s == 30.0


def test_wandb_section_round_trips() -> None:
    topo = parse_topology(_with_logging("  wandb: {project: p, name: n, tags: [x], init_timeout_s: 5}"), "t.yaml")
    assert parse_topology(dump_topology_yaml(topo), "t.yaml") == topo


@pytest.mark.parametrize("section, path, words", [
    ("  wandb: {project: p, mode: onlin}", "logging.wandb.mode", "did you mean 'online'?"),
    ("  wandb: {project: p, mode: disabled}", "logging.wandb.mode", "expected offline, online"),
    ("  wandb: {project: p, projekt: q}", "logging.wandb.projekt", "did you mean 'project'?"),
    ("  wandb: {mode: offline}", "logging.wandb.project", "missing required key 'project'"),
    ("  wandb: {project: ''}", "logging.wandb.project", "empty project"),
    ("  wandb: {project: 'me/p'}", "logging.wandb.project", "invalid W&B project"),
    ("  wandb: {project: p, tags: ['']}", "logging.wandb.tags[0]", "invalid W&B tag"),
    ("  wandb: {project: p, init_timeout_s: 0}", "logging.wandb.init_timeout_s", "out of range"),
    ("  wandb: {project: p, finish_timeout_s: -1}", "logging.wandb.finish_timeout_s", "out of range"),
    ("  wand: {project: p}", "logging.wand", "did you mean 'wandb'?"),
    ("  wandb: my-project", "logging.wandb", "expected a mapping or null"),
])
def test_bad_wandb_sections_are_one_line_naming_the_key(section: str, path: str, words: str) -> None:
    problems = _problems(_with_logging(section))
    assert len(problems) == 1, problems
    line = problems[0]
    assert line.startswith("tiny.yaml:") and f": {path}: " in line and words in line, line
    assert "\n" not in line


def test_missing_wandb_package_is_one_line_at_dvla_up(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "wandb" else real(name, *a))
    topo = tmp_path / "tiny-wandb.yaml"
    topo.write_text(_with_logging("  wandb: {project: p}"))
    res = CliRunner().invoke(app, ["up", str(topo), "--runs", str(tmp_path / "runs")])
    assert res.exit_code != 0
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1, res.output
    assert "logging.wandb" in lines[0] and "pip install 'dvla[wandb]'" in lines[0] and str(topo) in lines[0]
    assert not (tmp_path / "runs").exists()  # refused before anything was created
    assert missing_wandb(parse_topology(TINY)) is None  # nothing to check without logging.wandb


def test_open_hint_names_the_sync_command_or_the_project(tmp_path: Path) -> None:
    assert open_hint(WandbConfig(project="p"), tmp_path).startswith(f"wandb sync {tmp_path / 'wandb'}/offline-run-*")
    assert "W&B project p" in open_hint(WandbConfig(project="p", mode="online"), tmp_path)


# ------------------------------------------------------------------------------------------
# the W&B thread, against a stand-in wandb module


class FakeRun:
    def __init__(self, finish_blocks: threading.Event | None = None) -> None:
        self.rows: list[dict[str, Any]] = []
        self.metrics: list[tuple[str, str | None]] = []
        self.finished = False
        self.settings = types.SimpleNamespace(sync_dir="/runs/x/wandb/offline-run-1")
        self.url = "https://wandb.example/run"
        self._finish_blocks = finish_blocks

    def define_metric(self, name: str, step_metric: str | None = None) -> None:
        self.metrics.append((name, step_metric))

    def log(self, row: dict[str, Any]) -> None:
        self.rows.append(row)

    def finish(self) -> None:
        if self._finish_blocks is not None:
            self._finish_blocks.wait()
        self.finished = True


def fake_wandb(monkeypatch: pytest.MonkeyPatch, init: Any) -> types.ModuleType:
    """A stand-in `wandb` module whose `init` is `init`; records what it was given."""
    module = types.ModuleType("wandb")
    module.inits = []  # type: ignore[attr-defined]
    module.teardowns = 0  # type: ignore[attr-defined]

    class Settings(dict):
        model_fields = {"init_timeout": None, "finish_timeout": None}

        def __init__(self, **kw: Any) -> None:
            super().__init__(**kw)

    def _init(**kw: Any) -> Any:
        module.inits.append(kw)  # type: ignore[attr-defined]
        return init(**kw)

    def _teardown() -> None:
        module.teardowns += 1  # type: ignore[attr-defined]

    module.Settings = Settings  # type: ignore[attr-defined]
    module.init = _init  # type: ignore[attr-defined]
    module.teardown = _teardown  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "wandb", module)
    # the W&B thread sets these for the whole process: restored after the test
    monkeypatch.setenv("WANDB_ERROR_REPORTING", "true")
    monkeypatch.setenv("WANDB_SILENT", "true")
    return module


def _started(cfg: WandbConfig, tmp_path: Path) -> WandbLog:
    return WandbLog(cfg, tmp_path, "tiny", {"task": {"env": "PushCube-v1"}})


def _wait_for(predicate: Any, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_rounds_are_logged_by_env_steps_and_the_run_finished(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    run = FakeRun()
    wandb = fake_wandb(monkeypatch, lambda **kw: run)
    log = _started(WandbConfig(project="p", tags=("a",)), tmp_path)
    log.log(0, {"rollout/steps_per_s": 0.0})
    log.log(400, {"train/approx_kl": 0.01, "weights/version": 1.0})
    notes = log.close()
    init = wandb.inits[0]
    assert init["project"] == "p" and init["mode"] == "offline" and init["dir"] == str(tmp_path)
    assert init["name"] == "tiny" and init["group"] == "tiny" and init["tags"] == ["a"]
    assert init["config"] == {"task": {"env": "PushCube-v1"}}
    assert init["settings"]["init_timeout"] == 30.0 and init["settings"]["console"] == "off"
    assert run.metrics == [("env_steps", None), ("*", "env_steps")]
    assert run.rows == [{"env_steps": 0, "rollout/steps_per_s": 0.0},
                        {"env_steps": 400, "train/approx_kl": 0.01, "weights/version": 1.0}]
    assert run.finished and wandb.teardowns == 1
    assert notes == ["wandb: offline run in /runs/x/wandb/offline-run-1; upload it with: wandb sync /runs/x/wandb/offline-run-1"]


def test_log_never_waits_and_a_full_queue_drops_and_counts(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    released = threading.Event()
    run = FakeRun()

    def slow_init(**kw: Any) -> FakeRun:  # W&B still reaching its server
        released.wait()
        return run

    fake_wandb(monkeypatch, slow_init)
    monkeypatch.setattr(wandb_log, "QUEUE_ROUNDS", 4)
    log = _started(WandbConfig(project="p", mode="online"), tmp_path)
    logger = threading.Thread(target=lambda: [log.log(step, {"x": float(step)}) for step in range(10)], daemon=True)
    logger.start()
    logger.join(timeout=30)
    assert not logger.is_alive(), "log() waited for W&B's init, which holds until released"
    assert log.dropped == 6
    released.set()
    notes = log.close()
    assert [row["env_steps"] for row in run.rows] == [0, 1, 2, 3]
    assert notes == ["wandb: https://wandb.example/run", "logging.wandb: 6 round(s) of scalars not sent to W&B (queue full)"]


def test_failed_init_is_one_warning_and_later_rounds_are_ignored(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    def no_network(**kw: Any) -> None:
        raise TimeoutError("Timed out initializing run: context deadline exceeded\nConsider increasing init_timeout")

    wandb = fake_wandb(monkeypatch, no_network)
    log = _started(WandbConfig(project="p", mode="online"), tmp_path)
    notes: list[str] = []
    _wait_for(lambda: notes.extend(log.take_notes()) or notes)  # the warning: W&B is off by now
    log.log(1, {"x": 1.0})
    notes += log.close()
    assert len(notes) == 1, notes
    assert notes[0].startswith("warning: logging.wandb: W&B online run did not start (TimeoutError: Timed out")
    assert "Consider" not in notes[0] and "the run goes on without W&B" in notes[0]
    assert log.dropped == 0 and wandb.teardowns == 1


def test_close_is_bounded_when_finish_hangs(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    stuck = threading.Event()
    fake_wandb(monkeypatch, lambda **kw: FakeRun(finish_blocks=stuck))
    monkeypatch.setattr(wandb_log, "CLOSE_MARGIN_S", 0.2)
    log = _started(WandbConfig(project="p", finish_timeout_s=0.3), tmp_path)
    closed: list[list[str]] = []
    closer = threading.Thread(target=lambda: closed.append(log.close()), daemon=True)
    closer.start()
    closer.join(timeout=30)
    assert not closer.is_alive(), "close() waited for finish(), which holds until released"
    (notes,) = closed
    assert any(n.startswith("warning: logging.wandb: W&B did not finish within") for n in notes), notes
    stuck.set()

"""`dvla up`'s stop sequence (dvla/orchestrator/run.py `Up._shutdown`): the stop command is sent
again until each role has exited, so a role whose command subscriber was not yet declared when the
run ended (still starting) stops by itself instead of being waited for and then sent SIGTERM.
Pure logic: the launcher and the fabric are stand-ins that record what they are asked."""

from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

from dvla.orchestrator import run as run_mod


@dataclass
class _Child:
    kind: str
    #: stop commands this role misses before its subscriber exists (None: never stops by itself)
    deaf_for: int | None
    heard: int = 0
    gone: bool = False
    proc: SimpleNamespace = field(init=False)

    def __post_init__(self) -> None:
        self.proc = SimpleNamespace(config=SimpleNamespace(kind=self.kind))

    def alive(self) -> bool:
        return not self.gone


class _Launcher:
    def __init__(self, children: dict[str, _Child]) -> None:
        self.children = children
        self.stopped: list[str] = []
        self.order: list[str] = []

    def wait_exit(self, names: list[str], timeout: float) -> list[str]:
        return [n for n in names if self.children[n].alive()]

    def stop(self, names: list[str], timeout: float) -> None:
        self.stopped += names
        for n in names:
            self.children[n].gone = True

    def poll(self, stopping: bool) -> list[str]:
        return []


class _Fabric:
    def __init__(self, launcher: _Launcher) -> None:
        self.launcher = launcher
        self.keys = SimpleNamespace(cmd=lambda name: f"cmd/{name}")
        self.sent: list[str] = []

    def publish_ctrl(self, key: str, cmd: object) -> None:
        name = key.split("/", 1)[1]
        self.sent.append(name)
        child = self.launcher.children[name]
        self.launcher.order.append(child.kind)
        if child.deaf_for is not None:
            child.heard += 1
            if child.heard > child.deaf_for:  # subscribed by now: it stops and exits
                child.gone = True


def _shutdown(children: dict[str, _Child], monkeypatch, wait_s: float = 15.0) -> tuple[_Launcher, _Fabric, list[str]]:
    monkeypatch.setattr(run_mod, "STOP_RESEND_S", 0.0)  # no real waiting between the sends
    monkeypatch.setattr(run_mod, "STOP_WAIT_S", wait_s)
    launcher = _Launcher(children)
    fabric = _Fabric(launcher)
    up = object.__new__(run_mod.Up)
    up.launcher, up.events = launcher, []
    up._shutdown(fabric)
    return launcher, fabric, up.events


def test_a_role_that_was_still_starting_gets_the_stop_again_and_exits_by_itself(monkeypatch) -> None:
    children = {"rollout-0": _Child("rollout", 0), "evaluator-0": _Child("evaluator", 3),
                "actor-0": _Child("actor", 0), "replicator-0": _Child("replicator", 0)}
    launcher, fabric, events = _shutdown(children, monkeypatch)
    assert fabric.sent.count("evaluator-0") == 4 and fabric.sent.count("rollout-0") == 1
    assert launcher.stopped == [] and events == []
    assert all(not c.alive() for c in children.values())
    # leaves first: the actor and the relays are told only once every leaf is gone
    assert launcher.order.index("actor") > max(i for i, k in enumerate(launcher.order) if k == "evaluator")


def test_a_role_that_never_exits_is_terminated_after_the_wait(monkeypatch) -> None:
    children = {"rollout-0": _Child("rollout", None), "actor-0": _Child("actor", 0)}
    launcher, fabric, events = _shutdown(children, monkeypatch, wait_s=0.05)
    assert fabric.sent.count("rollout-0") >= 2  # sent again while it was waited for
    assert launcher.stopped == ["rollout-0"] and events == ["no clean exit from rollout-0: terminating"]
    assert fabric.sent.count("actor-0") == 1

"""Hostile topology files: each is refused with ``file:line: path: message`` lines, bounded in
time, memory and output, by the loader and by the real CLI (`dvla plan`, `dvla up`), never with a
traceback. See docs/security.md."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from dvla.config import MAX_SHOWN, host_problem
from dvla.orchestrator.topology import (
    MAX_DEPTH,
    MAX_FILE_BYTES,
    MAX_PROBLEMS,
    Problem,
    TopologyError,
    load_topology,
    parse_topology,
)

ROOT = Path(__file__).resolve().parents[2]

MINIMAL = """\
run: t
racks:
  - name: r0
    nodes:
      - name: n0
        roles: [{role: actor}, {role: rollout}]
"""


def _problems(text: str, source: str = "t.yaml") -> list[Problem]:
    with pytest.raises(TopologyError) as info:
        parse_topology(text, source)
    return info.value.problems


def _one(text: str) -> Problem:
    problems = _problems(text)
    assert len(problems) == 1, problems
    return problems[0]


def _with_kwargs(value: str) -> str:
    return MINIMAL + f"task:\n  policy_kwargs:\n    x: {value}\n"


# ------------------------------------------------------------------------------------------
# pathological YAML


@pytest.mark.parametrize("levels", [MAX_DEPTH + 1, 10_000])
def test_deep_flow_nesting_is_one_problem(levels: int) -> None:
    p = _one(_with_kwargs("[" * levels + "]" * levels))
    assert p.path == "<yaml>" and f"nested deeper than {MAX_DEPTH} levels" in p.message and p.line == 9


def test_deep_block_nesting_and_a_nested_root_are_one_problem() -> None:
    block = MINIMAL + "task:\n  policy_kwargs:\n    x:\n" + "".join("      " + "  " * i + "-\n" for i in range(500))
    assert "nested deeper" in _one(block).message
    assert "nested deeper" in _one("[" * 10_000 + "]" * 10_000).message


def test_nesting_within_the_limit_is_fine() -> None:
    levels = MAX_DEPTH - 4  # root mapping, task, policy_kwargs, x
    topo = parse_topology(_with_kwargs("[" * levels + "]" * levels))
    assert isinstance(topo.task.policy_kwargs["x"], list)


def test_alias_bomb_is_refused_quickly() -> None:
    lines = ["a0: &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 10)]  # 10^10 once expanded
    text = MINIMAL + "task:\n  policy_kwargs:\n" + "".join(f"    {line}\n" for line in lines)
    p = _one(text)  # refused as it is read: never expanded
    assert (p.line, p.path) == (9, "<yaml>") and "anchors and aliases are refused" in p.message


def test_recursive_alias_is_refused() -> None:
    assert "anchors and aliases are refused" in _one(_with_kwargs("&loop [1, *loop]")).message


def test_huge_file_is_refused_unread(tmp_path: Path) -> None:
    path = tmp_path / "huge.yaml"
    path.write_text(MINIMAL + ("# padding\n" * (MAX_FILE_BYTES // 10 + 1)))
    with pytest.raises(TopologyError) as info:
        load_topology(path)
    assert str(info.value) == f"{path}: <root>: file larger than {MAX_FILE_BYTES} bytes (a topology is a few KiB; refused unread)"
    assert "more than a topology needs" in _one(path.read_text()).message  # parse_topology on its own


def test_huge_values_are_not_echoed_in_full() -> None:
    big = "x" * 100_000
    for text in (MINIMAL.replace("run: t", f"run: {big}"), MINIMAL.replace("name: n0", f"name: n0\n        host: {big}"),
                 MINIMAL + f"task:\n  env: {big}\n  obs_mode: {big}\n", MINIMAL + f"seed: {'1' * 5000}\n"):
        problems = _problems(text)
        for p in problems:
            assert len(str(p)) < 400, str(p)[:500]
        assert any("characters)" in p.message or "digits" in p.message for p in problems)


@pytest.mark.parametrize("text,reason", [("seed: 2024-13-45", "month must be in 1..12"),
                                         ("seed: " + "9" * 5000, "Exceeds the limit (4300 digits)")])
def test_values_python_cannot_convert_are_one_problem(text: str, reason: str) -> None:
    p = _one(MINIMAL + text + "\n")
    assert p.path == "seed" and p.message.startswith("cannot read value: ") and reason in p.message


def test_values_are_shown_cut_to_the_limit() -> None:
    p = _one(MINIMAL.replace("run: t", "run: " + "Y" * 1000))
    shown = p.message.split("invalid run id ", 1)[1].split(" (1002 characters)")[0]
    assert len(shown) <= MAX_SHOWN and shown.endswith("...")


def test_control_characters_are_escaped() -> None:
    p = _one(MINIMAL.replace("name: n0", 'name: "\\e[2J\\nline"'))
    assert "\x1b" not in str(p) and "\n" not in str(p) and "\\x1b[2J" in str(p)


def test_problem_count_is_capped() -> None:
    text = MINIMAL + "".join(f"unknown_{i}: 1\n" for i in range(MAX_PROBLEMS + 50))
    problems = _problems(text)
    assert len(problems) == MAX_PROBLEMS + 1
    assert problems[-1].message == "50 more problem(s) from here on not shown"


# ------------------------------------------------------------------------------------------
# non-finite numbers


@pytest.mark.parametrize("literal", [".nan", ".NaN", ".inf", "-.inf", "+.Inf", "1e999", "-1e999"])
@pytest.mark.parametrize("path", ["task.ppo.lr", "links.node_gbit", "task.budget.max_wall_s", "simulate.hop_latency_s"])
def test_non_finite_numbers_are_refused(literal: str, path: str) -> None:
    *sections, key = path.split(".")
    text = MINIMAL + "".join(f"{'  ' * i}{name}:\n" for i, name in enumerate(sections)) + f"{'  ' * len(sections)}{key}: {literal}\n"
    p = _one(text)
    assert p.path == path and "is not a finite number" in p.message


@pytest.mark.parametrize("value", [".nan", "[1, 2, -.inf]", "{a: {b: [.inf]}}"])
def test_non_finite_numbers_in_free_form_values_are_refused(value: str) -> None:
    p = _one(_with_kwargs(value))
    assert p.path == "task.policy_kwargs.x" and "is not a finite number" in p.message


# ------------------------------------------------------------------------------------------
# names that become keys and process names


@pytest.mark.parametrize("name", ["a/b", "*", "$x", "a?b", "a#b", "-x", ".x", "a b", "ü", "x" * 65, ""])
def test_node_and_rack_names_must_be_one_key_chunk(name: str) -> None:
    quoted = repr(name)
    for text, path in ((MINIMAL.replace("name: n0", f"name: {quoted}"), "racks[0].nodes[0].name"),
                       (MINIMAL.replace("name: r0", f"name: {quoted}"), "racks[0].name")):
        p = _one(text)
        assert p.path == path and ("invalid" in p.message and "name" in p.message), p


def test_node_name_making_a_too_long_process_name() -> None:
    p = _one(MINIMAL.replace("name: n0", "name: " + "n" * 60))
    assert "makes process name 'rollout-nnn" in p.message and "longer than 64" in p.message


@pytest.mark.parametrize("name", ["n0", "gpu-7.lab", "A_b.c-1", "x" * 50])
def test_plain_names_are_fine(name: str) -> None:
    parse_topology(MINIMAL.replace("name: n0", f"name: {name}"))


# ------------------------------------------------------------------------------------------
# hosts and ssh settings (they end up on ssh's command line)

BAD_HOSTS = ["-oProxyCommand=touch pwned", "-p", "rl@gpu-7", "gpu 7", "gpu;id", "$(id)", "`id`", "a..b", ".a", "[gpu]",
             "[::1", "::g", "gpu/7", "gpu:22", "x" * 300, "gpu\tx", "-"]
GOOD_HOSTS = ["gpu-7.lab", "gpu-7.lab.", "10.1.0.7", "node_7", "::1", "[::1]", "fe80::1%eth0", "[2001:db8::7]", "GPU7"]


@pytest.mark.parametrize("host", BAD_HOSTS)
def test_bad_hosts_are_refused(host: str) -> None:
    assert host_problem(host) is not None
    text = MINIMAL.replace("name: n0", f"name: n0\n        host: {host!r}")
    p = _one(text)
    assert p.path == "racks[0].nodes[0].host" and "invalid host" in p.message, p


@pytest.mark.parametrize("host", GOOD_HOSTS)
def test_good_hosts_are_accepted(host: str) -> None:
    assert host_problem(host) is None


def test_address_is_checked_like_a_host() -> None:
    p = _one(MINIMAL.replace("name: n0", "name: n0\n        address: '10.0.0.1?iface=eth0'"))
    assert p.path == "racks[0].nodes[0].address" and "invalid address" in p.message


@pytest.mark.parametrize("user", ["-oProxyCommand=x", "a b", "rl@x", "a:b", "", "-"])
def test_bad_ssh_users_are_refused(user: str) -> None:
    p = _one(MINIMAL + f"ssh:\n  user: {user!r}\n")
    assert p.path == "ssh.user" and "invalid user" in p.message


def test_node_ssh_settings_are_checked_too() -> None:
    text = MINIMAL.replace("name: n0", "name: n0\n        ssh: {user: '-x', python: \"py\\nthon\"}")
    assert {p.path for p in _problems(text)} == {"racks[0].nodes[0].ssh.user", "racks[0].nodes[0].ssh.python"}


# ------------------------------------------------------------------------------------------
# user policies


def _policy(spec: str) -> str:
    return MINIMAL + f"task:\n  policy: {spec!r}\n  obs_mode: state\n"


def test_policy_that_does_not_import_is_refused() -> None:
    p = _one(_policy("no_such_module_xyz:Policy"))
    assert p.path == "task.policy"
    assert p.message == "cannot import policy 'no_such_module_xyz:Policy': ModuleNotFoundError: No module named 'no_such_module_xyz'"


@pytest.mark.parametrize("source,error", [("def broken(:\n", "SyntaxError"), ("import no_such_dep_xyz\n", "ModuleNotFoundError"),
                                          ("raise SystemExit(3)\n", "SystemExit"), ("1 / 0\n", "ZeroDivisionError")])
def test_policy_module_failing_on_import_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, source: str, error: str) -> None:
    module = f"hostile_policy_{error.lower()}"
    (tmp_path / f"{module}.py").write_text(source)
    monkeypatch.chdir(tmp_path)  # roles import with the working directory on the path: so does the check
    monkeypatch.delitem(sys.modules, module, raising=False)
    p = _one(_policy(f"{module}:Policy"))
    assert p.path == "task.policy" and f"cannot import policy '{module}:Policy': {error}" in p.message
    assert str(tmp_path) not in sys.path


def test_policy_class_missing_and_malformed_specs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "fine_policy_mod.py").write_text("class Policy:\n    pass\n")
    monkeypatch.chdir(tmp_path)
    parse_topology(_policy("fine_policy_mod:Policy"))
    assert "has no class 'Nope'" in _one(_policy("fine_policy_mod:Nope")).message
    assert "invalid policy" in _one(_policy(":Policy")).message
    assert "invalid policy" in _one(_policy("fine_policy_mod:")).message


# ------------------------------------------------------------------------------------------
# the real command line: one line on stderr, exit 2, nothing started

HOSTILE = {
    "deep.yaml": lambda: _with_kwargs("[" * 10_000 + "]" * 10_000),
    "bomb.yaml": lambda: (ROOT / "tests/unit/topologies_bad/alias_bomb.yaml").read_text(),
    "huge.yaml": lambda: MINIMAL + "#" * (MAX_FILE_BYTES + 1) + "\n",
    "bigvalue.yaml": lambda: MINIMAL.replace("run: t", "run: " + "z" * 200_000),
    "nan.yaml": lambda: MINIMAL + "task:\n  ppo:\n    lr: .nan\n",
    "host.yaml": lambda: MINIMAL.replace("name: n0", "name: n0\n        host: -oProxyCommand=touch pwned"),
    "name.yaml": lambda: MINIMAL.replace("name: n0", "name: 'n/*'"),
    "policy.yaml": lambda: _policy("no_such_module_xyz:Policy"),
}


def _check_refusal(path: Path, code: int, stdout: str, stderr: str, runs: Path) -> None:
    assert code == 2, stderr[-2000:]
    assert "Traceback" not in stderr and stdout == ""
    lines = stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{path}:") and len(lines[0]) < 400, stderr[:1000]
    assert not runs.exists() and not (path.parent / "pwned").exists()


@pytest.mark.parametrize("command", ["plan", "up"])
@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_cli_refuses_hostile_topology_in_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str,
                                                  command: str) -> None:
    from typer.testing import CliRunner

    from dvla.orchestrator.cli import app

    path = tmp_path / name
    path.write_text(HOSTILE[name]())
    runs = tmp_path / "runs"
    monkeypatch.chdir(tmp_path)
    args = [command, str(path)] + (["--runs", str(runs), "--quiet"] if command == "up" else [])
    res = CliRunner().invoke(app, args)
    assert isinstance(res.exception, SystemExit), res.exception  # typer.Exit(2), nothing else escaped
    _check_refusal(path, res.exit_code, res.stdout, res.stderr, runs)


@pytest.mark.parametrize("command,name", [("plan", "deep.yaml"), ("up", "host.yaml")])
def test_real_cli_process_refuses_in_one_line(tmp_path: Path, command: str, name: str) -> None:
    path = tmp_path / name
    path.write_text(HOSTILE[name]())
    runs = tmp_path / "runs"
    args = [command, str(path)] + (["--runs", str(runs), "--quiet"] if command == "up" else [])
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "dvla", *args], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=60)
    _check_refusal(path, res.returncode, res.stdout, res.stderr, runs)

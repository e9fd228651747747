"""Tests of topology parsing and validation (dvla.orchestrator.topology).

Each file in topologies_bad/ is a broken topology whose header says which problem must be
reported: ``# expect: <message substring>``, ``# expect-line: <line>``, ``# expect-path: <key path>``.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from dvla.config import ENCODINGS, LinkConfig, NodeConfig, RackConfig, RolePlacement, TaskConfig, Topology
from dvla.orchestrator.topology import (
    Problem,
    TopologyError,
    dump_topology_yaml,
    load_topology,
    parse_topology,
    topology_to_dict,
)

HERE = Path(__file__).resolve().parent
BAD_DIR = HERE / "topologies_bad"
TOPOLOGY_DIR = HERE.parents[1] / "topologies"
BAD_FILES = sorted(BAD_DIR.glob("*.yaml"))
GOOD_FILES = sorted(TOPOLOGY_DIR.glob("*.yaml"))
#: local-libero.yaml names LIBERO's assets beside the repository: without them it cannot load
_LIBERO_ASSETS = (TOPOLOGY_DIR / "../../shared/libero-assets").resolve()
_REFERENCES = (TOPOLOGY_DIR / "../../shared/reference-checkpoints").resolve()  # where the shipped files point


def _shipped(p: Path) -> object:
    """A shipped topology, skipped where what it names beside the repository is absent."""
    if "libero" in p.name and not _LIBERO_ASSETS.is_dir():
        return pytest.param(p, marks=pytest.mark.skip(reason=f"no LIBERO assets at {_LIBERO_ASSETS}"))
    if "../shared/reference-checkpoints" in p.read_text() and not _REFERENCES.is_dir():
        return pytest.param(p, marks=pytest.mark.skip(reason=f"no reference checkpoints at {_REFERENCES}"))
    return p


SHIPPED = [_shipped(p) for p in GOOD_FILES]

#: every problem renders as file:line: key.path: message
PROBLEM_LINE_RE = re.compile(r"^.+:\d+: \S+: .+$")

MINIMAL = """\
run: t
racks:
  - name: r0
    nodes:
      - name: n0
        roles:
          - role: actor
          - role: rollout
"""


def _header(path: Path) -> dict[str, str]:
    found = dict(re.findall(r"^# (expect|expect-line|expect-path): (.*)$", path.read_text(), re.M))
    missing = {"expect", "expect-line", "expect-path"} - found.keys()
    if missing:
        pytest.fail(f"{path.name} lacks header(s) {sorted(missing)}")
    return found


def _problems(text: str, source: str = "t.yaml") -> list[Problem]:
    with pytest.raises(TopologyError) as info:
        parse_topology(text, source)
    return info.value.problems


# ------------------------------------------------------------------------------------------
# malformed files


def test_enough_bad_files() -> None:
    assert len(BAD_FILES) >= 30


@pytest.mark.parametrize("path", BAD_FILES, ids=lambda p: p.name)
def test_bad_file_reports_expected_problem(path: Path) -> None:
    want = _header(path)
    with pytest.raises(TopologyError) as info:
        load_topology(path)
    text = str(info.value)
    prefix = f"{path.name}:{want['expect-line']}: {want['expect-path']}: "
    hits = [line for line in text.splitlines() if prefix in line and want["expect"] in line]
    assert hits, f"expected a problem starting {prefix!r} containing {want['expect']!r}, got:\n{text}"


@pytest.mark.parametrize("path", BAD_FILES, ids=lambda p: p.name)
def test_every_problem_is_one_formatted_line(path: Path) -> None:
    with pytest.raises(TopologyError) as info:
        load_topology(path)
    lines = str(info.value).splitlines()
    assert len(lines) == len(info.value.problems)
    for line in lines:
        assert PROBLEM_LINE_RE.match(line), line
        assert line.startswith(str(path) + ":")


def test_independent_problems_are_all_reported() -> None:
    text = """\
run: Bad Id
task:
  envs_per_rollout: 0
racks:
  - name: r0
    nodes:
      - name: n0
        roles:
          - role: actor
          - role: rollout
            cnt: 2
"""
    problems = _problems(text)
    assert [(p.line, p.path) for p in problems] == [
        (1, "run"),
        (3, "task.envs_per_rollout"),
        (11, "racks[0].nodes[0].roles[1].cnt"),
    ]


def test_problems_in_sibling_and_nested_objects_do_not_hide_each_other() -> None:
    text = MINIMAL + (
        "links:\n  node_gbit: 0\n"
        "replication:\n  encoding: zip\n  fanout: zero\n"
        "task:\n  ppo:\n    gamma: 2.0\n"
    )
    paths = {p.path for p in _problems(text)}
    assert {"links.node_gbit", "replication.encoding", "replication.fanout", "task.ppo.gamma"} <= paths


def test_unknown_role_does_not_also_claim_the_actor_is_missing() -> None:
    text = MINIMAL.replace("role: actor", "role: learner")
    problems = _problems(text, "8node.yaml")
    assert [str(p) for p in problems] == [
        "8node.yaml:7: racks[0].nodes[0].roles[0].role: unknown role 'learner' "
        "(expected actor, rollout, replicator, evaluator)"
    ]


def test_problems_are_sorted_by_line() -> None:
    text = "seed: x\nbase_port: 1\n" + MINIMAL.replace("run: t", "run: T")
    problems = _problems(text)
    assert [(p.line, p.path) for p in problems] == [(1, "seed"), (2, "base_port"), (3, "run")]


def test_anchors_aliases_and_merge_keys_are_refused() -> None:
    """No topology needs them, and a few aliases make a small file stand for 10^9 values."""
    text = MINIMAL.replace("      - name: n0\n", "      - &worker\n        name: n0\n")
    assert [str(p) for p in _problems(text)] == ["t.yaml:5: <yaml>: YAML anchors and aliases are refused (write the value out)"]
    text = MINIMAL.replace("roles:\n", "roles: *just_rollout\n")
    assert "anchors and aliases are refused" in _problems(text)[0].message
    text = MINIMAL + "task:\n  <<: {env: PushCube-v1}\n"
    ((line, path, message),) = [(p.line, p.path, p.message) for p in _problems(text)]
    assert (line, path) == (10, "task") and message.startswith("merge keys ('<<') are refused")


# ------------------------------------------------------------------------------------------
# scalar typing


def test_bool_is_not_accepted_as_int() -> None:
    for field in ("seed: true", "base_port: false"):
        (problem,) = _problems(MINIMAL + field + "\n")
        assert "expected an integer, got boolean" in problem.message


def test_bool_is_not_accepted_as_float() -> None:
    (problem,) = _problems(MINIMAL + "links:\n  node_gbit: true\n")
    assert problem.path == "links.node_gbit"
    assert "expected a number, got boolean true" in problem.message


def test_int_is_accepted_as_float() -> None:
    topo = parse_topology(MINIMAL + "links:\n  node_gbit: 2\n")
    assert topo.links.node_gbit == 2.0 and type(topo.links.node_gbit) is float


def test_exponent_without_dot_is_a_float() -> None:
    # YAML 1.1 reads 3e-4 as a string; nobody writing a learning rate means that
    topo = parse_topology(MINIMAL + "task:\n  ppo:\n    lr: 3e-4\n")
    assert topo.task.ppo.lr == pytest.approx(3e-4)


def test_quoted_number_is_not_a_float() -> None:
    (problem,) = _problems(MINIMAL + "task:\n  ppo:\n    lr: '0.001'\n")
    assert problem.path == "task.ppo.lr" and "got string '0.001'" in problem.message


def test_optional_fields_accept_null() -> None:
    topo = parse_topology(MINIMAL + "task:\n  budget:\n    max_env_steps: null\n    max_wall_s: 60\n")
    assert topo.task.budget.max_env_steps is None
    assert topo.task.budget.max_wall_s == 60.0


def test_dates_and_numbers_are_not_strings() -> None:
    problems = _problems(MINIMAL.replace("run: t", "run: 2024-01-01").replace("name: n0", "name: 0"))
    assert [p.message for p in problems] == [
        "expected a string, got date 2024-01-01 (quote it to make it a string)",
        "expected a string, got integer 0 (quote it to make it a string)",
    ]


def test_policy_kwargs_take_any_values() -> None:
    topo = parse_topology(MINIMAL + "task:\n  policy_kwargs:\n    hidden: [256, 256]\n    act: tanh\n")
    assert topo.task.policy_kwargs == {"hidden": [256, 256], "act": "tanh"}


def test_cpus_become_a_tuple() -> None:
    topo = parse_topology(MINIMAL.replace("        roles:", "        cpus: [2, 3]\n        roles:"))
    assert topo.racks[0].nodes[0].cpus == (2, 3)


# ------------------------------------------------------------------------------------------
# semantics not covered by one bad file each


def test_defaults_apply() -> None:
    topo = parse_topology(MINIMAL)
    assert topo.task == TaskConfig()
    assert topo.links == LinkConfig()
    assert topo.racks == (
        RackConfig(
            name="r0",
            nodes=(NodeConfig(name="n0", roles=(RolePlacement(role="actor"), RolePlacement(role="rollout"))),),
        ),
    )


def test_every_encoding_is_accepted() -> None:
    for encoding in ENCODINGS:
        assert parse_topology(MINIMAL + f"replication:\n  encoding: {encoding}\n").replication.encoding == encoding


def test_netns_accepts_local_hosts() -> None:
    text = MINIMAL.replace("      - name: n0\n", "      - name: n0\n        host: 127.0.0.1\n")
    assert parse_topology(text + "emulate: netns\n").emulate == "netns"


def test_remote_host_is_fine_without_netns() -> None:
    text = MINIMAL.replace("      - name: n0\n", "      - name: n0\n        host: gpu-7.lab\n")
    assert parse_topology(text).racks[0].nodes[0].host == "gpu-7.lab"


def test_single_envs_per_rollout_is_allowed() -> None:
    assert parse_topology(MINIMAL + "task:\n  envs_per_rollout: 1\n").task.envs_per_rollout == 1


def test_until_success_alone_is_a_stop_condition() -> None:
    text = MINIMAL + "task:\n  budget:\n    max_env_steps: null\n    until_success: 1\n"
    assert parse_topology(text).task.budget.until_success == 1.0


def test_secret_file_resolves_relative_to_the_topology(tmp_path: Path) -> None:
    (tmp_path / "keys").mkdir()
    secret = tmp_path / "keys" / "cluster.secret"
    secret.write_text("00" * 32)
    topo_file = tmp_path / "t.yaml"
    topo_file.write_text(MINIMAL + "secret_file: keys/cluster.secret\n")
    topo = load_topology(topo_file)
    assert topo.secret_file == str(secret)
    assert topo.source == str(topo_file)


def test_missing_secret_file_names_the_resolved_path(tmp_path: Path) -> None:
    topo_file = tmp_path / "t.yaml"
    topo_file.write_text(MINIMAL + "secret_file: nope.secret\n")
    with pytest.raises(TopologyError) as info:
        load_topology(topo_file)
    assert str(tmp_path / "nope.secret") in str(info.value)


def test_unreadable_file_is_a_topology_error(tmp_path: Path) -> None:
    with pytest.raises(TopologyError) as info:
        load_topology(tmp_path / "absent.yaml")
    assert "absent.yaml" in str(info.value) and "cannot read" in str(info.value)


def test_source_defaults_to_memory() -> None:
    assert parse_topology(MINIMAL).source == "<memory>"


def test_error_is_a_value_error_with_problem_list() -> None:
    with pytest.raises(ValueError) as info:
        parse_topology("run: t\n", "x.yaml")
    assert isinstance(info.value, TopologyError)
    assert all(isinstance(p, Problem) for p in info.value.problems)


# ------------------------------------------------------------------------------------------
# shipped topologies and round trip


def test_shipped_topologies_exist() -> None:
    assert {p.name for p in GOOD_FILES} >= {"local.yaml", "8node.yaml", "tiny.yaml"}


def _prepare(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """local-hf-vla.yaml and gpu-vla-rl.yaml name a checkpoint their headers say how to write:
    written here (at the test size: the file is under test, not the 0.5 B weights), in a temp
    directory that becomes the working directory (the path is relative)."""
    ckpt = {"local-hf-vla.yaml": "runs/ckpt/vla-tokens", "gpu-vla-rl.yaml": "runs/ckpt/vla-tokens-0.5b"}.get(path.name)
    if ckpt is not None:
        from dvla.learn.vla.build import main as build

        monkeypatch.chdir(tmp_path)
        assert build([ckpt, "--family", "tokens"]) == 0


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_topology_loads(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _prepare(path, tmp_path, monkeypatch)
    topo = load_topology(path)
    assert topo.source == str(path)
    kinds = {placement.role for _, node in topo.nodes() for placement in node.roles}
    assert {"actor", "rollout"} <= kinds


def test_local_topology() -> None:
    topo = load_topology(TOPOLOGY_DIR / "local.yaml")
    assert topo.run == "local"
    ((rack, node),) = topo.nodes()
    assert (rack.name, node.name, node.host) == ("rack0", "node0", "localhost")
    assert {p.role: p.count for p in node.roles} == {"actor": 1, "replicator": 1, "rollout": 2, "evaluator": 1}
    assert topo.task.env == "PushCube-v1" and topo.task.obs_mode == "state" and topo.task.algorithm == "ppo"
    # the stop rule of docs/evaluation.md: one 128-episode evaluation whose lower bound clears 0.75
    b = topo.task.budget
    assert (b.max_env_steps, b.until_success, b.success_on, b.consecutive) == (300_000, 0.75, "lower_bound", 1)
    assert topo.task.eval.episodes == 128
    assert topo.replication.encoding == "full"


def test_8node_topology() -> None:
    topo = load_topology(TOPOLOGY_DIR / "8node.yaml")
    assert (topo.run, topo.emulate) == ("cluster8", "netns")
    names = [node.name for _, node in topo.nodes()]
    assert names == [f"r{r}n{n}" for r in range(2) for n in range(4)]
    roles = {node.name: sorted(p.role for p in node.roles for _ in range(p.count)) for _, node in topo.nodes()}
    assert roles["r0n0"] == ["actor", "evaluator", "rollout"]
    assert [n for n, r in roles.items() if "replicator" in r] == ["r0n1", "r1n0"]
    assert all(r.count("rollout") == 1 for r in roles.values())
    assert (topo.links.node_gbit, topo.links.rack_uplink_gbit) == (1.0, 0.2)
    assert (topo.replication.encoding, topo.replication.fanout) == ("full", 6)


def test_tiny_topology() -> None:
    topo = load_topology(TOPOLOGY_DIR / "tiny.yaml")
    ((_, node),) = topo.nodes()
    assert {p.role: p.count for p in node.roles} == {"actor": 1, "replicator": 1, "rollout": 2, "evaluator": 1}
    assert (topo.task.envs_per_rollout, topo.task.chunk_steps) == (2, 10)
    assert topo.task.budget.max_env_steps == 3000
    ppo = topo.task.ppo
    assert (ppo.batch_steps, ppo.minibatches, ppo.update_epochs) == (400, 4, 2)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_round_trip_of_shipped_topologies(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _prepare(path, tmp_path, monkeypatch)
    topo = load_topology(path)
    assert parse_topology(dump_topology_yaml(topo), topo.source) == topo


def test_round_trip_of_non_default_values(tmp_path: Path) -> None:
    secret = tmp_path / "s.key"
    secret.write_text("ab" * 32)
    topo = parse_topology(MINIMAL + f"secret_file: {secret}\n")
    node = dataclasses.replace(topo.racks[0].nodes[0], host="10.0.0.7", address="10.0.0.7", cpus=(0, 5))
    topo = dataclasses.replace(
        topo,
        seed=7,
        mode="sync",
        shared_memory=True,
        racks=(dataclasses.replace(topo.racks[0], nodes=(node,)),),
        task=dataclasses.replace(topo.task, policy_kwargs={"hidden": [64, 64], "act": "yes"}, device="cpu"),
        links=LinkConfig(node_gbit=0.125, rack_uplink_gbit=1e-3),
    )
    again = parse_topology(dump_topology_yaml(topo))
    assert again == topo
    assert parse_topology(dump_topology_yaml(again)) == again


def test_topology_to_dict_is_plain() -> None:
    def plain(value: object) -> bool:
        if isinstance(value, dict):
            return all(isinstance(k, str) and plain(v) for k, v in value.items())
        if isinstance(value, list):
            return all(plain(v) for v in value)
        return value is None or type(value) in (str, int, float, bool)

    d = topology_to_dict(load_topology(TOPOLOGY_DIR / "8node.yaml"))
    assert plain(d)
    assert "source" not in d
    assert isinstance(d["racks"], list) and isinstance(d["racks"][0]["nodes"][0]["roles"], list)
    assert set(d) == {f.name for f in dataclasses.fields(Topology)} - {"source"}


def test_a_hf_policys_checkpoint_is_checked_before_anything_starts(tmp_path: Path) -> None:
    """vla-tokens / vla-flow: no checkpoint, a missing or incomplete directory, or one of the
    other family is one problem line naming the key and the path (the CLI prints it, no traceback)."""
    from dvla.learn.vla.build import save_random_checkpoint

    flow = save_random_checkpoint(tmp_path / "flow", "flow", action_dim=8, max_chunk=2)
    base = MINIMAL + "task:\n  obs_mode: rgb\n  policy: vla-tokens\n"
    (msg,) = [p.message for p in _problems(base)]
    assert "needs policy_kwargs.checkpoint" in msg
    cases = {
        str(tmp_path / "nope"): "does not exist",
        str(flow): "'flow' checkpoint",
    }
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "config.json").write_text("{}")
    cases[str(tmp_path / "half")] = "safetensors"
    for path, what in cases.items():
        problems = _problems(base + f"  policy_kwargs: {{checkpoint: {path}}}\n")
        assert len(problems) == 1 and problems[0].path == "task.policy_kwargs.checkpoint", problems
        assert path in problems[0].message and what in problems[0].message and "\n" not in problems[0].message
    # the right family loads
    ok = MINIMAL + f"task:\n  obs_mode: rgb\n  policy: vla-flow\n  policy_kwargs: {{checkpoint: {flow}}}\n"
    assert parse_topology(ok, "t.yaml").task.policy == "vla-flow"


def test_a_published_checkpoint_is_checked_before_anything_starts(tmp_path: Path) -> None:
    """pi0 / pi05 / smolvla: a missing directory or repo id, another family's directory, weights
    of another architecture than config.json says, or truncated weights are one problem line
    naming the key and the path (nothing is loaded: file and header checks only)."""
    import json
    import shutil

    from tests.references.conftest import reference_dir

    pi05, smolvla = reference_dir("pi05"), reference_dir("smolvla")
    base = MINIMAL + "task:\n  obs_mode: rgb\n  policy: pi05\n"
    (msg,) = [p.message for p in _problems(base)]
    assert "needs policy_kwargs.checkpoint" in msg
    liar = tmp_path / "liar"  # pi0 weights under a config that says pi05
    shutil.copytree(reference_dir("pi0"), liar)
    cfg = json.loads((liar / "config.json").read_text())
    (liar / "config.json").write_text(json.dumps({**cfg, "type": "pi05"}))
    cut = tmp_path / "cut"
    shutil.copytree(pi05, cut)
    (cut / "model.safetensors").write_bytes((pi05 / "model.safetensors").read_bytes()[:100_000])
    cases = {
        str(tmp_path / "nope"): "does not exist",
        "someone/not-cached": "Hugging Face cache",
        str(smolvla): "smolvla",
        str(liar): "pi0",
        str(cut): "truncated",
    }
    for path, what in cases.items():
        problems = _problems(base + f"  policy_kwargs: {{checkpoint: {path}}}\n")
        assert len(problems) == 1 and problems[0].path == "task.policy_kwargs.checkpoint", (path, problems)
        assert path in problems[0].message and what in problems[0].message and "\n" not in problems[0].message
    ok = base + f"  policy_kwargs: {{checkpoint: {pi05}}}\n"
    assert parse_topology(ok, "t.yaml").task.policy == "pi05"


def test_the_schemas_policy_list_is_the_registry() -> None:
    """A topology may name exactly the built-in policies (besides "module:Class"). Checked in a
    fresh interpreter: other tests register policies of their own in this one."""
    import subprocess
    import sys

    code = ("from dvla.config import POLICY_OBS; from dvla.learn.policies import registered_policies; "
            "print(sorted(POLICY_OBS) == registered_policies(), sorted(POLICY_OBS), registered_policies())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stdout.startswith("True"), out.stdout + out.stderr
    (problem,) = _problems(MINIMAL + "task:\n  policy: mpl\n")
    assert problem.path == "task.policy" and "did you mean 'mlp'?" in problem.message


#: MINIMAL with its roles in flow style
FLOW = MINIMAL.replace("        roles:\n          - role: actor\n          - role: rollout\n",
                       "        roles: [{role: actor}, {role: rollout}]\n")


@pytest.mark.parametrize("value, expected", [("2", 2), ("0", 0), ("auto", "auto")])
def test_sim_workers_is_a_count_or_auto(value: str, expected: object) -> None:
    text = FLOW.replace("{role: rollout}", f"{{role: rollout, sim_workers: {value}}}")
    placement = parse_topology(text).racks[0].nodes[0].roles[1]
    assert placement.sim_workers == expected and type(placement.sim_workers) is type(expected)


@pytest.mark.parametrize("roles, message", [
    ("{role: rollout, sim_workers: many}", "expected an integer or one of auto, got string 'many'"),
    ("{role: rollout, sim_workers: -1}", "-1 (expected 0 for none, a number of worker processes, or auto)"),
    ("{role: rollout, sim_workers: true}", "expected an integer or one of auto, got boolean true"),
    ("{role: rollout, sim_workers: [2]}", "expected an integer or one of auto, got a list"),
])
def test_bad_sim_workers_are_refused_naming_the_key(roles: str, message: str) -> None:
    with pytest.raises(TopologyError) as info:
        parse_topology(FLOW.replace("{role: rollout}", roles), "t.yaml")
    text = str(info.value)
    assert "roles[1].sim_workers" in text and message in text, text


def test_sim_workers_belong_to_rollouts() -> None:
    with pytest.raises(TopologyError, match=r"roles\[0\]\.sim_workers: 2 is a rollout setting, this placement is a actor"):
        parse_topology(FLOW.replace("{role: actor}", "{role: actor, sim_workers: 2}"), "t.yaml")


def test_up_options_override_the_budget_mode_seed_and_warm_start() -> None:
    """`dvla up --max-env-steps/--mode/--seed/--init-weights` replace the topology's values;
    options left unset keep them."""
    from dvla.orchestrator.run import UpOptions, apply_overrides

    topo = load_topology(Path(__file__).resolve().parents[2] / "topologies" / "tiny.yaml")
    same = apply_overrides(topo, UpOptions())
    assert same == topo
    got = apply_overrides(topo, UpOptions(max_env_steps=123, mode="sync", seed=7, init_weights="/w/bc.safetensors"))
    assert (got.task.budget.max_env_steps, got.mode, got.seed, got.task.init_weights) == (123, "sync", 7, "/w/bc.safetensors")
    assert got.task.budget.until_success == topo.task.budget.until_success and got.racks == topo.racks


def test_obs_mode_rgb_plus_state_is_an_rgb_mode_for_policies() -> None:
    """``rgb+state`` (images + the privileged state vector as proprio) is read by the rgb
    policies; a state policy, or a mode nobody knows, is one problem line naming the key."""
    ok = MINIMAL + "task:\n  obs_mode: rgb+state\n  policy: tiny-vla\n"
    assert parse_topology(ok, "t.yaml").task.obs_mode == "rgb+state"
    (problem,) = _problems(MINIMAL + "task:\n  obs_mode: rgb+state\n  policy: mlp\n")
    assert problem.path == "task.policy" and "'state' observations" in problem.message
    assert "'rgb+state'" in problem.message
    (problem,) = _problems(MINIMAL + "task:\n  obs_mode: rgb+depth\n  policy: tiny-vla\n")
    assert problem.path == "task.obs_mode" and "expected state, rgb, rgb+state" in problem.message

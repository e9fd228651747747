"""Checkpoints (dvla.roles.checkpoint): a round trip, and files that would run code if unpickled
are refused with one line naming the file, never loaded. See docs/security.md."""

from __future__ import annotations

import hashlib
import json
import pickle
from pathlib import Path

import pytest
import torch

from dvla.roles.checkpoint import (MANIFEST, CheckpointError, load_checkpoint, load_init_weights, optimizer_tensors,
                                   save_checkpoint)


class _Payload:
    """Unpickling this creates `path`: what a hostile checkpoint would do, with any command."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def __reduce__(self):  # type: ignore[no-untyped-def]
        return (open, (self.path, "w"))


def _checksum(policy: torch.nn.Module) -> str:
    h = hashlib.sha256()
    for name, t in sorted(policy.state_dict().items()):
        h.update(name.encode() + t.detach().numpy().tobytes())
    return h.hexdigest()[:16]


def _trained() -> tuple[torch.nn.Module, torch.optim.Optimizer]:
    torch.manual_seed(0)
    policy = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(policy.parameters(), lr=1e-3)
    policy(torch.ones(4, 3)).sum().backward()
    opt.step()
    return policy, opt


@pytest.fixture
def ckpt(tmp_path: Path) -> Path:
    policy, opt = _trained()
    directory = tmp_path / "checkpoints"
    save_checkpoint(directory, policy.state_dict(), optimizer_tensors(opt), 7, 1234, _checksum(policy))
    return directory


def _fresh() -> tuple[torch.nn.Module, torch.optim.Optimizer]:
    policy = torch.nn.Linear(3, 2)
    return policy, torch.optim.Adam(policy.parameters(), lr=1e-3)


def _replace(directory: Path, name: str, data: bytes, manifest_name: str | None = None) -> Path:
    """Put `data` in the current checkpoint as `name`, with the manifest's sha256 matching (an
    attacker who can write the run directory can rewrite the manifest too)."""
    manifest = json.loads((directory / MANIFEST).read_text())
    path = directory / manifest["dir"] / name
    path.write_bytes(data)
    manifest["files"][manifest_name or name] = hashlib.sha256(data).hexdigest()
    (directory / MANIFEST).write_text(json.dumps(manifest))
    return path


def test_round_trip_restores_weights_and_optimizer(ckpt: Path) -> None:
    saved_policy, saved_opt = _trained()
    policy, opt = _fresh()
    got = load_checkpoint(ckpt, policy, opt, _checksum)
    assert got is not None and (got.version, got.env_steps) == (7, 1234)
    assert _checksum(policy) == _checksum(saved_policy)
    state, want = opt.state_dict()["state"], saved_opt.state_dict()["state"]
    assert state.keys() == want.keys()
    assert all(torch.equal(state[i]["exp_avg"], want[i]["exp_avg"]) for i in state)


def test_payload_is_live(tmp_path: Path) -> None:
    """The payload used below really runs when unpickled (so the tests below mean something)."""
    marker = tmp_path / "ran"
    pickle.loads(pickle.dumps(_Payload(marker)))
    assert marker.exists()


@pytest.mark.parametrize("name", ["optimizer.safetensors", "policy.safetensors"])
@pytest.mark.parametrize("how", ["pickle", "torch.save"])
def test_pickled_checkpoint_file_is_refused_unread(ckpt: Path, tmp_path: Path, name: str, how: str) -> None:
    marker = tmp_path / "pwned"
    if how == "pickle":
        data = pickle.dumps({"state": _Payload(marker)})
    else:
        buf = tmp_path / "evil.pt"
        torch.save({"state": _Payload(marker)}, buf)
        data = buf.read_bytes()
    path = _replace(ckpt, name, data)
    policy, opt = _fresh()
    before = _checksum(policy)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(ckpt, policy, opt, _checksum)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "refused" in message and "\n" not in message
    assert not marker.exists()
    assert _checksum(policy) == before  # nothing applied


def test_protocol_0_pickle_is_refused_too(ckpt: Path, tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    path = _replace(ckpt, "optimizer.safetensors", pickle.dumps(_Payload(marker), protocol=0))
    with pytest.raises(CheckpointError, match="not a safetensors file") as info:
        load_checkpoint(ckpt, *_fresh(), _checksum)
    assert str(info.value).startswith(f"{path}: ") and not marker.exists()


def test_extra_pickle_file_in_the_manifest_is_refused(ckpt: Path, tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    _replace(ckpt, "optimizer.pt", pickle.dumps(_Payload(marker)))
    with pytest.raises(CheckpointError, match="does not name a checkpoint") as info:
        load_checkpoint(ckpt, *_fresh(), _checksum)
    assert str(info.value).startswith(f"{ckpt / MANIFEST}: ") and not marker.exists()


@pytest.mark.parametrize("value", ["../elsewhere", "/tmp", "v0000001", None])
def test_manifest_dir_outside_the_checkpoints_is_refused(ckpt: Path, value: object) -> None:
    manifest = json.loads((ckpt / MANIFEST).read_text())
    manifest["dir"] = value
    (ckpt / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(CheckpointError, match="does not name a checkpoint"):
        load_checkpoint(ckpt, *_fresh(), _checksum)


@pytest.mark.parametrize("text", ["[]", '{"dir": "v00000007"}', '{"dir": "v00000007", "files": {}, "version": "x",'
                                  ' "env_steps": 1, "checksum": "c"}'])
def test_malformed_manifest_is_one_error(ckpt: Path, text: str) -> None:
    (ckpt / MANIFEST).write_text(text)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(ckpt, *_fresh(), _checksum)
    assert str(info.value).startswith(f"{ckpt / MANIFEST}: ")


def test_another_policy_shape_is_refused_and_nothing_applied(ckpt: Path) -> None:
    policy = torch.nn.Linear(3, 5)
    before = _checksum(policy)
    with pytest.raises(CheckpointError, match="policy.safetensors"):
        load_checkpoint(ckpt, policy, torch.optim.Adam(policy.parameters()), _checksum)
    assert _checksum(policy) == before


# --- warm starts (task.init_weights) ------------------------------------------------------------


def test_init_weights_from_a_file_and_from_a_checkpoints_directory(ckpt: Path, tmp_path: Path) -> None:
    """A warm start loads what the policy replicates, from a safetensors file or from a run's
    current checkpoint; the policy then holds exactly those tensors."""
    from safetensors.torch import save_file

    trained, _ = _trained()
    file = tmp_path / "bc.safetensors"
    save_file({k: v.contiguous() for k, v in trained.state_dict().items()}, str(file))
    for source in (file, ckpt):
        policy, _ = _fresh()
        assert not torch.equal(policy.weight, trained.weight)
        described = load_init_weights(source, policy)
        assert str(source) in described
        assert torch.equal(policy.weight, trained.weight) and torch.equal(policy.bias, trained.bias)


@pytest.mark.parametrize("tensors,fault", [
    ({"weight": torch.zeros(2, 3)}, "missing ['bias']"),
    ({"weight": torch.zeros(2, 3), "bias": torch.zeros(2), "head.w": torch.zeros(1)}, "unexpected ['head.w']"),
    ({"weight": torch.zeros(3, 2), "bias": torch.zeros(2)}, "weight has shape (3, 2)"),
    ({"weight": torch.zeros(2, 3), "bias": torch.tensor([0.0, float("nan")])}, "bias holds non-finite"),
    ({"weight": torch.zeros(2, 3, dtype=torch.int64), "bias": torch.zeros(2)}, "weight is torch.int64"),
])
def test_an_init_weights_file_of_another_policy_is_refused_naming_the_key(tmp_path: Path, tensors: dict,
                                                                         fault: str) -> None:
    from safetensors.torch import save_file

    file = tmp_path / "other.safetensors"
    save_file(tensors, str(file))
    policy, _ = _fresh()
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    with pytest.raises(CheckpointError) as err:
        load_init_weights(file, policy)
    assert str(file) in str(err.value) and fault in str(err.value), err.value
    assert all(torch.equal(before[k], v) for k, v in policy.state_dict().items())  # nothing applied


def test_init_weights_refuses_a_pickle_and_an_empty_directory(tmp_path: Path) -> None:
    pickled = tmp_path / "policy.pt"
    torch.save(torch.nn.Linear(3, 2).state_dict(), pickled)
    with pytest.raises(CheckpointError, match="pickle"):
        load_init_weights(pickled, _fresh()[0])
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="without a checkpoint"):
        load_init_weights(tmp_path / "empty", _fresh()[0])


def test_a_safetensors_file_whose_header_length_starts_0x80_is_not_taken_for_a_pickle(tmp_path: Path) -> None:
    """A safetensors file begins with its header's length (8 bytes, little-endian): one header in
    256 has 0x80 as the first byte, pickle's protocol-2 magic. Such a file still loads."""
    from safetensors.torch import save_file

    from dvla.learn.checkpoint_files import read_safetensors

    file = tmp_path / "w.safetensors"
    for pad in range(300):
        save_file({"w": torch.ones(2)}, str(file), metadata={"pad": "x" * pad})
        if file.read_bytes()[0] == 0x80:
            break
    assert file.read_bytes()[0] == 0x80
    tensors, meta = read_safetensors(file)
    assert torch.equal(tensors["w"], torch.ones(2)) and meta["pad"]

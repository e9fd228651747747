"""Every test under tests/references/ is marked ``references`` (``pytest -m references`` runs
exactly them) and finds its checkpoints through :func:`reference_root`."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
REFERENCES_ENV = "DVLA_REFERENCE_CHECKPOINTS"
OFT_REFERENCES_ENV = "DVLA_REFERENCE_CHECKPOINTS_OFT"


def reference_root() -> Path:
    """``$DVLA_REFERENCE_CHECKPOINTS``, else ``../shared/reference-checkpoints`` beside the repository."""
    return Path(os.environ.get(REFERENCES_ENV) or ROOT.parent / "shared" / "reference-checkpoints").resolve()


def reference_dir(name: str) -> Path:
    """One policy directory (``pi0``, ``pi05``, ``smolvla``) of the reference set; the test is
    skipped, naming the path and the variable, when the set does not hold it."""
    path = reference_root() / name
    if not (path / "reference" / "reference.safetensors").is_file():
        pytest.skip(f"reference checkpoint {path} not found: set {REFERENCES_ENV} or keep ../shared/reference-checkpoints")
    return path


def load_reference(name: str) -> dict:
    """The recorded arrays of ``reference/reference.safetensors`` as torch tensors."""
    from safetensors.torch import load_file

    return load_file(str(reference_dir(name) / "reference" / "reference.safetensors"))


def oft_reference_root() -> Path:
    """``$DVLA_REFERENCE_CHECKPOINTS_OFT``, else ``../shared/reference-checkpoints-oft``; the test
    is skipped, naming the path and the variable, when it holds no OpenVLA reference set."""
    path = Path(os.environ.get(OFT_REFERENCES_ENV) or ROOT.parent / "shared" / "reference-checkpoints-oft").resolve()
    if not (path / "reference" / "openvla_reference.safetensors").is_file():
        pytest.skip(f"OpenVLA reference checkpoints {path} not found: set {OFT_REFERENCES_ENV} or keep "
                    "../shared/reference-checkpoints-oft")
    return path


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    here = Path(__file__).parent
    for item in items:
        if here in Path(str(item.fspath)).parents:
            item.add_marker(pytest.mark.references)

"""Session-wide test settings."""

from __future__ import annotations

import os
import shutil
import tempfile

import pytest

_CACHE: str | None = None
_BASETEMP: str | None = None


def pytest_configure(config: object) -> None:
    # PyTorch's fused CPU Adam creates a kernel-cache directory, by default under /tmp: give the
    # test session (and every process it starts) its own, removed when the session ends.
    global _CACHE
    if "TORCHINDUCTOR_CACHE_DIR" not in os.environ:
        _CACHE = tempfile.mkdtemp(prefix="dvla-tests-torchinductor-")
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = _CACHE
    # Every tmp_path (run directories, checkpoints, logs) under one directory of this session,
    # removed when it ends, instead of pytest's kept /tmp/pytest-of-<user>/pytest-N.
    global _BASETEMP
    option = getattr(config, "option", None)
    if option is not None and getattr(option, "basetemp", None) is None:
        _BASETEMP = tempfile.mkdtemp(prefix="dvla-tests-")
        option.basetemp = _BASETEMP


def pytest_unconfigure(config: object) -> None:
    if _CACHE is not None:
        shutil.rmtree(_CACHE, ignore_errors=True)
        os.environ.pop("TORCHINDUCTOR_CACHE_DIR", None)
    if _BASETEMP is not None:
        shutil.rmtree(_BASETEMP, ignore_errors=True)


@pytest.fixture(scope="module")
def one_torch_thread():
    """torch on one thread for a module (the same figures on every machine, no contention with
    the suite); used by modules that train, through ``pytest.mark.usefixtures``."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def pytest_collection_modifyitems(config: object, items: list) -> None:
    # Under pytest-xdist (`-n 2 --dist loadgroup`, as `make test` runs), tests that use something
    # only one of them can hold at a time run on one worker, one after the other: the emulated
    # clusters (`netns`) route the host's 10.77.0.0/16 to their bridge, and the Slurm tests count
    # the machine's Slurm daemons before and after.
    for item in items:
        if item.get_closest_marker("netns") is not None or item.get_closest_marker("slurm") is not None:
            item.add_marker(pytest.mark.xdist_group("machine-wide"))

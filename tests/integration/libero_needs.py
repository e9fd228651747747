"""What LIBERO's tests need, and the reason they skip without it: the hf-libero package (the
``libero`` extra) and LIBERO's assets (``$DVLA_LIBERO_ASSETS``, else ``../shared/libero-assets``
beside the repository: the libero_spatial subset)."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

from dvla.config import LIBERO_ASSETS_ENV, libero_assets_problem

ROOT = Path(__file__).resolve().parents[2]


def libero_assets() -> Path:
    """Where the tests look for LIBERO's assets."""
    return Path(os.environ.get(LIBERO_ASSETS_ENV) or ROOT.parent / "shared" / "libero-assets").resolve()


def skip_reason() -> str | None:
    """Why LIBERO's tests cannot run here, or None."""
    if importlib.util.find_spec("libero") is None or importlib.util.find_spec("robosuite") is None:
        return ("hf-libero is not installed: bash scripts/setup.sh libero (the libero extra, with pip held to the "
                "installed torch and numpy; docs/libero.md)")
    problem = libero_assets_problem(str(libero_assets()))
    if problem:
        return f"LIBERO assets not found: set {LIBERO_ASSETS_ENV} or keep ../shared/libero-assets ({problem})"
    return None


#: marks a test (or module) that runs real LIBERO envs
requires_libero = pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")

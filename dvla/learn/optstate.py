"""Optimizer state as named tensors plus JSON, never a pickle: for checkpoints (safetensors) and
for handing rank 0's state to the other ranks of the learner group. Tensors of
``optimizer.state_dict()`` become ``state.<index>.<name>``; numbers and param groups go to the JSON.
"""

from __future__ import annotations

import json
from typing import Any

import torch
from torch import Tensor


def optimizer_to_tensors(sd: dict[str, Any]) -> tuple[dict[str, Tensor], str]:
    """(tensors, JSON) of an optimizer state dict; tensors are detached copies on the CPU."""
    tensors: dict[str, Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for index, entry in sd["state"].items():
        for name, value in entry.items():
            if isinstance(value, Tensor):
                tensors[f"state.{index}.{name}"] = value.detach().to("cpu", copy=True).contiguous()
            else:
                scalars.setdefault(str(index), {})[name] = value
    return tensors, json.dumps({"param_groups": sd["param_groups"], "scalars": scalars}, sort_keys=True)


def optimizer_from_tensors(tensors: dict[str, Tensor], meta: str, like: dict[str, Any]) -> dict[str, Any]:
    """The state dict :func:`optimizer_to_tensors` made ``(tensors, meta)`` from. ``like`` is the
    receiving optimizer's own state dict: its parameter indices must be the ones saved. Raises
    ValueError naming what does not fit."""
    doc = json.loads(meta)
    groups = doc["param_groups"]
    want = [i for g in like["param_groups"] for i in g["params"]]
    got = [i for g in groups for i in g["params"]]
    if want != got:
        raise ValueError(f"optimizer state is for parameters {got[:4]}... ({len(got)}), this optimizer has {len(want)}")
    state: dict[int, dict[str, Any]] = {}
    for key, t in tensors.items():
        prefix, index, name = key.split(".", 2)
        if prefix != "state" or int(index) not in want:
            raise ValueError(f"optimizer state has an unexpected tensor {key!r}")
        state.setdefault(int(index), {})[name] = t
    for index, values in doc["scalars"].items():
        state.setdefault(int(index), {}).update(values)
    return {"state": state, "param_groups": groups}

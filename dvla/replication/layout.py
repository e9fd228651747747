"""Parameter layout: the map between a torch state_dict and one flat float32 vector.

Owns :class:`ParamLayout`, :func:`flatten`, :func:`unflatten_into` and :func:`bind_flat`, and
the root of the replication errors (:class:`ReplicationError`, :class:`LayoutMismatch`).

Only floating-point tensors that can change replicate: a frozen parameter (``requires_grad=False``,
a LoRA base, docs/policies.md) is loaded from the same checkpoint on every node, and integer
buffers (BatchNorm's ``num_batches_tracked``) are learner bookkeeping. Every tensor travels as
float32 (float16 and bfloat16 convert exactly, float64 is rounded).
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Union

import numpy as np
import torch

StateDictLike = Union[torch.nn.Module, Mapping[str, torch.Tensor]]
"""Anything the layout functions read tensors from: a module or a name -> tensor mapping."""


class ReplicationError(Exception):
    """Base class of every error raised by ``dvla.replication`` for bad input or state."""


class LayoutMismatch(ReplicationError):
    """Two sides disagree on which tensors are replicated or on their shapes/dtypes."""


@dataclass(frozen=True)
class ParamLayout:
    """Ordered names, shapes and dtypes of the replicated (floating) tensors of a model.

    The order is the state_dict order, which torch keeps deterministic for a given module
    definition, so the actor and every rollout building the same policy class agree on it.
    """

    #: tensor names, in flat-vector order
    names: tuple[str, ...]
    #: tensor shapes, parallel to ``names``
    shapes: tuple[tuple[int, ...], ...]
    #: torch dtype names (e.g. "float32"), parallel to ``names``
    dtypes: tuple[str, ...]
    #: start offset (in elements) of each tensor in the flat vector; derived
    offsets: tuple[int, ...] = field(init=False, repr=False, compare=False)
    #: total number of elements; derived
    numel: int = field(init=False, compare=False)
    #: hex digest of names, shapes and dtypes; derived
    hash: str = field(init=False, compare=False)

    def __post_init__(self) -> None:
        if not (len(self.names) == len(self.shapes) == len(self.dtypes)):
            raise ValueError("names, shapes and dtypes must have the same length")
        if len(set(self.names)) != len(self.names):
            raise ValueError("tensor names must be unique")
        offsets, total = [], 0
        for shape in self.shapes:
            offsets.append(total)
            total += math.prod(shape)
        object.__setattr__(self, "offsets", tuple(offsets))
        object.__setattr__(self, "numel", total)
        object.__setattr__(self, "hash", _layout_digest(self.names, self.shapes, self.dtypes))

    @staticmethod
    def from_state_dict(sd: StateDictLike) -> "ParamLayout":
        """The layout of the floating tensors of ``sd`` (a module or a state_dict); of a module,
        without its frozen parameters (see :func:`replicated_tensors`)."""
        names, shapes, dtypes = [], [], []
        for name, tensor in _state_dict(sd).items():
            if not torch.is_floating_point(tensor):
                continue
            names.append(name)
            shapes.append(tuple(int(s) for s in tensor.shape))
            dtypes.append(_dtype_name(tensor.dtype))
        return ParamLayout(names=tuple(names), shapes=tuple(shapes), dtypes=tuple(dtypes))

    @staticmethod
    def opaque(layout_hash: str, numel: int) -> "ParamLayout":
        """A layout known only by its hash and size, as a relay learns it from a verified
        manifest: it can decode, verify and forward versions without building the model."""
        if not 0 < numel < 2**32:
            raise ValueError(f"layout size {numel} out of range")
        layout = ParamLayout(names=("<flat>",), shapes=((int(numel),),), dtypes=("float32",))
        object.__setattr__(layout, "hash", str(layout_hash))
        return layout

    @property
    def nbytes(self) -> int:
        """Size in bytes of the flat float32 vector (also the size of a full payload)."""
        return 4 * self.numel

    def span(self, i: int) -> tuple[int, int]:
        """(start, stop) element offsets of tensor ``i`` in the flat vector."""
        start = self.offsets[i]
        return start, start + math.prod(self.shapes[i])


def _layout_digest(names: tuple[str, ...], shapes: tuple[tuple[int, ...], ...], dtypes: tuple[str, ...]) -> str:
    # Canonical JSON so the digest depends only on the content, never on Python's repr details.
    text = json.dumps([[n, list(s), d] for n, s, d in zip(names, shapes, dtypes)], separators=(",", ":"))
    return hashlib.blake2b(text.encode("utf-8"), digest_size=16).hexdigest()


def _dtype_name(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def replicated_tensors(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The state dict entries of ``module`` that replicate: all but frozen parameters
    (``requires_grad=False``; tied names of a frozen tensor included). Non-floating entries are
    dropped later by the layout."""
    frozen = {name for name, p in module.named_parameters(remove_duplicate=False) if not p.requires_grad}
    return {k: v for k, v in module.state_dict().items() if k not in frozen}


def _state_dict(sd: StateDictLike) -> Mapping[str, torch.Tensor]:
    # Module.state_dict() returns detached tensors that share storage with the parameters, so
    # in-place copies into them update the module itself.
    return replicated_tensors(sd) if isinstance(sd, torch.nn.Module) else sd


def _check_flat(flat: np.ndarray, layout: ParamLayout) -> None:
    if not isinstance(flat, np.ndarray) or flat.dtype != np.float32 or flat.shape != (layout.numel,):
        raise LayoutMismatch(
            f"flat vector must be float32 of shape ({layout.numel},), got "
            f"{getattr(flat, 'dtype', type(flat).__name__)} {getattr(flat, 'shape', '')}"
        )
    if not flat.flags.c_contiguous:
        raise LayoutMismatch("flat vector must be C-contiguous")


def _tensor_for(tensors: Mapping[str, torch.Tensor], layout: ParamLayout, i: int) -> torch.Tensor:
    name = layout.names[i]
    tensor = tensors.get(name)
    if tensor is None:
        raise LayoutMismatch(f"tensor {name!r} of the layout is missing")
    if tuple(tensor.shape) != layout.shapes[i]:
        raise LayoutMismatch(f"tensor {name!r} has shape {tuple(tensor.shape)}, layout says {layout.shapes[i]}")
    return tensor


def flatten(sd: StateDictLike, layout: ParamLayout, out: np.ndarray | None = None) -> np.ndarray:
    """Copy the layout's tensors of ``sd`` into one flat float32 vector and return it.

    With ``out`` (a C-contiguous float32 vector of ``layout.numel`` elements) nothing is
    allocated: the tensors are copied straight into it (from any device, converting dtype).
    """
    if out is None:
        out = np.zeros(layout.numel, dtype=np.float32)
    else:
        _check_flat(out, layout)
    tensors = _state_dict(sd)
    # A torch view of the numpy buffer lets Tensor.copy_ do device transfer and dtype
    # conversion in one pass, with no intermediate copy.
    out_t = torch.from_numpy(out)
    with torch.no_grad():
        for i in range(len(layout.names)):
            tensor = _tensor_for(tensors, layout, i)
            start, stop = layout.span(i)
            out_t[start:stop].view(layout.shapes[i]).copy_(tensor.detach())
    return out


def unflatten_into(flat: np.ndarray, model_or_state_dict: StateDictLike, layout: ParamLayout) -> None:
    """Copy ``flat`` into the existing tensors of a module or state_dict, in place.

    Nothing is allocated: ``Tensor.copy_`` from views of ``flat`` converts dtype and device.
    Tensors outside the layout are left untouched.
    """
    _check_flat(flat, layout)
    with warnings.catch_warnings():
        if not flat.flags.writeable:
            # A read-only source (e.g. np.frombuffer over bytes) is only read here; torch's
            # warning about non-writable arrays does not apply.
            warnings.simplefilter("ignore", UserWarning)
        src = torch.from_numpy(flat)
    tensors = _state_dict(model_or_state_dict)
    with torch.no_grad():
        for i in range(len(layout.names)):
            tensor = _tensor_for(tensors, layout, i)
            start, stop = layout.span(i)
            tensor.copy_(src[start:stop].view(layout.shapes[i]))


def bind_flat(module: torch.nn.Module, layout: ParamLayout) -> torch.Tensor | None:
    """Make the layout's tensors of ``module`` views into one flat tensor; return it.

    Installing a version is then one ``flat.copy_(src)`` instead of one copy per tensor; values,
    :func:`unflatten_into` and ``state_dict`` keep working. The flat tensor has the tensors' own
    dtype. Returns None, changing nothing, when the tensors do not share one dtype and device or
    a layout name is not a parameter or buffer of ``module``.
    """
    owners: list[tuple[torch.nn.Module, str, bool]] = []
    devices, dtypes = set(), set()
    for name, dtype in zip(layout.names, layout.dtypes):
        path, _, attr = name.rpartition(".")
        try:
            owner = module.get_submodule(path) if path else module
        except AttributeError:
            return None
        if attr in owner._parameters and owner._parameters[attr] is not None:
            tensor, is_param = owner._parameters[attr], True
        elif attr in owner._buffers and owner._buffers[attr] is not None:
            tensor, is_param = owner._buffers[attr], False
        else:
            return None
        if _dtype_name(tensor.dtype) != dtype:
            return None
        devices.add(tensor.device)
        dtypes.add(tensor.dtype)
        owners.append((owner, attr, is_param))
    if len(devices) > 1 or len(dtypes) > 1:
        return None
    device = devices.pop() if devices else torch.device("cpu")
    flat = torch.empty(layout.numel, dtype=dtypes.pop() if dtypes else torch.float32, device=device)
    with torch.no_grad():
        for i, (owner, attr, is_param) in enumerate(owners):
            start, stop = layout.span(i)
            view = flat[start:stop].view(layout.shapes[i])
            if is_param:
                param = owner._parameters[attr]
                view.copy_(param)
                param.data = view  # the same Parameter object, now stored in `flat`
            else:
                view.copy_(owner._buffers[attr])
                owner._buffers[attr] = view
    return flat

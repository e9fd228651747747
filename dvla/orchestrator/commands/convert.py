"""`dvla convert CHECKPOINT`: an OpenVLA-OFT directory's pickled heads written once as safetensors."""

from __future__ import annotations

from typing import Annotated, Optional

import typer

from .common import fail


def convert(
    checkpoint: Annotated[str, typer.Argument(help="an OpenVLA-OFT directory (or a cached repo id)")],
    chunk_size: Annotated[Optional[int], typer.Option(help="OFT's chunk when the platform is not LIBERO / ALOHA / "
                                                            "BRIDGE")] = None,
) -> None:
    """Write each `.pt` component (action head, proprio projector) as `<stem>.safetensors` beside it,
    read with `torch.load(weights_only=True)` after a check that it holds tensors only: every
    role then reads the safetensors and no host unpickles anything."""
    from ...learn.vla.checkpoint import CheckpointError
    from ...learn.vla.openvla_format import check_openvla, convert_components

    try:
        written = convert_components(check_openvla(checkpoint, "openvla-oft", chunk_size=chunk_size))
    except (CheckpointError, ValueError) as err:
        raise fail(str(err)) from None
    for path in written:
        typer.echo(f"wrote {path}")
    if not written:
        typer.echo("nothing to convert: every component already has its safetensors")

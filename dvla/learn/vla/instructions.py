"""Default language instructions of ManiSkill3 tasks (a topology may set its own).

The wording describes what the camera shows and what success means for each task, so the
instruction is consistent with the reward. A task missing here needs ``task.instruction`` in
the topology when it is observed in ``rgb`` mode.
"""

from __future__ import annotations

__all__ = ["INSTRUCTIONS", "instruction_for"]

INSTRUCTIONS: dict[str, str] = {
    "PushCube-v1": "push the cube to the red and white target",
    "PullCube-v1": "pull the cube back to the red and white target",
    "PokeCube-v1": "use the peg to poke the cube to the goal",
    "PickCube-v1": "pick up the cube and move it to the goal position",
    "StackCube-v1": "stack the red cube on top of the green cube",
    "PushT-v1": "push the t shaped block onto the t shaped target",
    "LiftPegUpright-v1": "lift the peg and stand it upright",
    "PegInsertionSide-v1": "insert the peg into the hole from the side",
    "PlugCharger-v1": "plug the charger into the receptacle",
    "RollBall-v1": "roll the ball to the goal region",
    "PullCubeTool-v1": "use the tool to pull the cube closer",
    "PlaceSphere-v1": "place the sphere into the bin",
    "TurnFaucet-v1": "turn the faucet handle",
    "OpenCabinetDrawer-v1": "open the cabinet drawer",
}
"""ManiSkill3 env id -> instruction."""


def instruction_for(env: str) -> str:
    """The table's instruction for ``env`` (callers put ``task.instruction`` first)."""
    try:
        return INSTRUCTIONS[env]
    except KeyError:
        raise ValueError(
            f"no default instruction for env {env!r}; set task.instruction in the topology "
            f"(known: {', '.join(sorted(INSTRUCTIONS))})"
        ) from None

"""Role processes (rollout, actor, replicator) and the swimlane threading they share."""

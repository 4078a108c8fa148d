"""The training stages: the Lightning module of each stage kind, its callbacks (held-apart
validation, keeping the best nets), the stage cache and the schedule that trains the chain stage by
stage (docs/architecture.md)."""

"""The main command's Hydra app: one job's lifecycle (job) and one sweep's parent run and report
(callbacks). It sits above the pipeline and reporting; ``python -m demon_lab`` runs it
(docs/architecture.md)."""

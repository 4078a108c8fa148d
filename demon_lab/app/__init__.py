"""The main command's Hydra app: one job's lifecycle (job), the sweeper that launches a sweep's jobs
(sweeper), and one sweep's parent run, failed jobs and report (callbacks). It sits above the pipeline
and reporting; ``python -m demon_lab`` runs it (docs/architecture.md)."""

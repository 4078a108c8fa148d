"""Reporting: the terminal tables, sample panels, study reports and figures from tracked runs, and
the MLflow dashboard. It reads the pipeline's store and imports nothing above it
(docs/architecture.md)."""

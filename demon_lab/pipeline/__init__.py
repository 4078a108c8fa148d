"""The pipeline: a config made into objects and checked (config, validate), the keys that make runs
and stages the same (identity), weights files, the MLflow store (tracking), the training stages and
their cache (stages) and the evaluation on the test sets (evaluate). It imports the model library
(core, nets, data, baselines) and nothing above it (docs/architecture.md)."""

"""The other commands' code: bench, device_check, diagnose, data_stats, convert (with its reader of
TensorFlow checkpoints, tf_checkpoint). Each is run as ``python -m demon_lab.NAME``; they sit at the
top beside the app and import any layer below (docs/architecture.md)."""

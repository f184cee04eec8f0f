"""Orchestration only: CLI, config schema, DAG, fingerprints, executors and logs."""

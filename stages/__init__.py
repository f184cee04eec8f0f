"""One thin module per DAG step. Each defines `STAGE = Stage(...)` (see pipeline.stage)."""

"""Evaluation of GST models against exact truth, and run time against error.

- `truth`: synthetic-scene truth mapped onto extracted crops;
- `evaluator`: per-crop pose errors and per-view novel-view scores;
- `summary`: breakdowns per camera, motion and body part;
- `evaluate`: `evaluate_model`, the one call that does all of it;
- `report`: summary.json, report.md, CSVs, plots and the side-by-side image;
- `bench`: the run-time-versus-error sweep over model variants.
"""

"""Single-image pose from landmarks: the landmark-world dataset, the detection noise model, a
render-free sampler and the pretraining of the landmark -> body path (docs/landmark_prior.md)."""

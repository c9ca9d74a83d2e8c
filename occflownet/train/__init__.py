"""Training: configuration, data pipeline, optimisation loop with EMA, checkpoints, resume and DDP."""

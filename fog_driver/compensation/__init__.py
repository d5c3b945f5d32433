"""Temperature-drift compensation: model-rate blocks, input features, the three stages, models and the pipeline."""

"""Temperature-drift compensation, arrays in, arrays out (no file is opened here: model files are
``fog_driver.modelfiles``', captures ``fog_driver.samples``', files in and out ``fog_driver.offline``'s):
model-rate blocks, input features, the three stages, the streaming models (``models``), their fitting
(``fitting``), the pipeline and its online adaptation."""

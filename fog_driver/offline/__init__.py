"""Files in, files out: fitting a model to captures, compensating a capture, the CSV rows."""

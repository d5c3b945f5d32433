"""The file vocabulary every layer shares: safe YAML reading and writing (``yamlio``), what a file is and
the checks before an output is written (``outputs``)."""

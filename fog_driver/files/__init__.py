"""The file vocabulary every layer shares: safe YAML reading and writing (``yamlio``), configs checked against
their dataclasses with one-line errors (``typed_mapping``, msgspec), what a file is and the checks before an
output is written (``outputs``)."""

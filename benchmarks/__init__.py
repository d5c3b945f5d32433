"""The benchmarks: each a module run from the repository's top as ``python -m benchmarks.NAME``; ``python -m
benchmarks`` runs the quick ones and rewrites their figure blocks (``__main__.py``); what they share is
``_harness.py``."""

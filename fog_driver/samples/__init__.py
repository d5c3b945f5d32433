"""Frames -> samples: protocol v1's stream (``stream``), any registered format's (``sources``), capture files
and their provenance sidecars (``captures``), and recording a port to a capture (``record``)."""

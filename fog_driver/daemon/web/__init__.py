"""The daemon's web view and Prometheus ``/metrics`` (the ``web`` extra): the server, what the page shows,
the metrics."""

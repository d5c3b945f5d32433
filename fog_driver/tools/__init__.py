"""The operator's tools, clients of ``fog-driver run`` built on ``fog_driver.client``: ``watch`` and ``ctl``."""

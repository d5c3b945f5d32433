"""The headless daemon (``fog-driver run``): always-on raw capture, systemd integration."""

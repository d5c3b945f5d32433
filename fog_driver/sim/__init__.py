"""Instrument simulator: thermal chamber, FOG physics, frame emission and live serving."""

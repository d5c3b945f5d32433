"""The lab's side of a calibration: chamber programs, turntable motion plans, the profiles and their YAML, ``plan``."""

"""The simulated instrument and its simulated lab: the gyro (``gyro``) and its thermal model (``thermal``), the
instrument that emits frames (``instrument``: ``Simulator``), faults (``faults``), a drawn population of
instruments (``population``), captures to files with their truth and table log (``capture``), serving live on a
pty (``serve``, ``kvh_device``) and table logs wrong on purpose, for tests (``tablelog``).

It runs the lab's programs (``fog_driver.lab``: the chamber program, the motion plan, the profiles): the layers put
it above the lab and below the daemon and the command line.
"""

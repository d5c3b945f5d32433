"""The lab's side of a calibration: what the chamber and the turntable are told to do over a run, whether a real
lab or the simulator (``fog_driver.sim``, which runs these programs) carries it out.

- ``program``: the chamber program (``ChamberProfile``: holds, ramps, steps, sinusoids), the air temperature over
  a run in closed form;
- ``motion``: the turntable's motion plan (``MotionPlan``: constant rates, positioning sequences, creeps) and the
  dwells it makes;
- ``profiles``: a run's profile, its chamber program and motion plan together (``SimProfile``), the built-in ones
  and the YAML profile files;
- ``plan``: a calibration program for the user's chamber (``fog-driver plan``), designed so that the drift fit
  can identify every time scale and term;
- ``checks``: the checks of a profile's numbers.

The layers: below ``fog_driver.sim``, above ``fog_driver.compensation`` (``plan`` reads the fitting's constants).
"""

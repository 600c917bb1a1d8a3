"""Host algorithms in numpy / scipy: no device buffers, no launches.

Closed forms and the parts of the seed's algorithms that are not per-pixel device work: GBR
(uncalibrated factorisation and its ambiguity, :mod:`gpps.host.gbr`), DGMC's highlight detection
and start selection (:mod:`gpps.host.dgmc`), the integrator's system assembly
(:mod:`gpps.host.poisson`), the perspective closed forms (:mod:`gpps.host.perspective`), the
single-image helpers (:mod:`gpps.host.single`), light calibration from spheres
(:mod:`gpps.host.calibrate`), automatic masks, accuracy measures and the analytic test scenes.
"""

"""Training- and evaluation-time code (data generators): never imported by the runtime package.

:mod:`gpps.training.mitsuba_scenes` renders photometric-stereo captures with Mitsuba 3, an optional
dependency (``pip install gpps[render]``).  tests/test_layers.py keeps every runtime layer from importing
this package.
"""

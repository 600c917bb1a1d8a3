"""Flows: whole reconstructions built from the stages of :mod:`gpps.pipeline` and the host algorithms
of :mod:`gpps.host`.  Their entry points are the public API, listed in :mod:`gpps`.
"""

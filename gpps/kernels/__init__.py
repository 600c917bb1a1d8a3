"""Device math (Warp): ``@wp.struct``, ``@wp.func`` and ``@wp.kernel`` only.

Nothing here allocates; the stages in :mod:`gpps.pipeline` own buffers and
launches.  Import submodules after :func:`gpps._runtime.warp` has initialised Warp.
"""

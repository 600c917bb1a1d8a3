"""Profiling kernels of the fused Poisson integrator, built from the parts the package's kernels use.

:func:`gpps.kernels.poisson_fused.make_fused` returns, with its kernels, the
namespace ``parts`` of the fields and ti.funcs they are built from; the
kernels here run pieces of the frame alone (one V-cycle, the coarsest solve,
an empty task) to time them.  Only the perf scripts use them
(``integration_device_speed.py``, ``integration_launch_overhead.py``,
``taichi_grid_barrier.py``), so they live here, not in the package.
"""

from gpps._taichi import ti


def profiling_kernels(K: dict) -> dict:
    """The profiling kernels over the fields of one :func:`~gpps.kernels.poisson_fused.make_fused` build.

    Args:
        K: the dict that ``make_fused`` returned (``StreamIntegrator._K``).

    Returns:
        dict of kernels: ``vcycle_only()`` (one V-cycle on the current level-0 ``f``),
        ``coarse_only()`` (the coarsest-level solve alone), ``noop()`` (one empty task: the
        launch overhead).
    """
    parts = K["parts"]
    sc, vcycle, coarse_solve = parts.sc, parts.vcycle, parts.coarse_solve

    @ti.kernel
    def vcycle_only():
        """One V-cycle on the current level-0 ``f`` (profiling)."""
        vcycle()

    @ti.kernel
    def coarse_only():
        """The coarsest-level solve alone (profiling)."""
        coarse_solve()

    @ti.kernel
    def noop():
        """One empty task (profiling: the launch overhead)."""
        for i in range(1):
            sc[6] += 0

    return {"vcycle_only": vcycle_only, "coarse_only": coarse_only, "noop": noop}

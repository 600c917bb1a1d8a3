"""Per-pixel calibrated photometric stereo: one thread solves one pixel.

Device math only; buffers and launches live in :mod:`gpps.pipeline.solver`.

Image model per light k and channel c (seed 4.1-4.2, 2.30-2.31)::

    I_kc = E_kc(p) * ( kd_c * max(n.l_k, 0) + ks * s(n, l_k, v) )

with ``l_k``, ``E_kc`` from :func:`gpps.kernels.brdf.light_dir` and
:func:`gpps.kernels.brdf.light_radiance` at the surface point ``p`` that the
pixel sees at the given depth (per-pixel direction and 1/r^2 fall-off for
point lights), ``v`` the view direction.

Unknowns: the normal, 2 degrees of freedom through the chart of
:mod:`gpps.kernels.jacobians` (re-centred on the current normal, so no
singularity anywhere on the visible hemisphere), and the albedo (1 or 3
channels).  The albedo enters linearly and is eliminated by *variable
projection*: for a given normal ``kd_c = sum_k w a y / sum_k w a^2`` with
``a_kc = E_kc max(n.l_k, 0)`` (plastic: its diffuse factor, which depends on
``n.v`` too, :func:`gpps.kernels.brdf.plastic_diffuse`), ``y_kc = I_kc - E_kc ks s_k``; the solvers then
minimise the reduced cost ``F(x) = 1/2 sum_kc w_k (y_kc - kd_c(x) a_kc)^2`` over
the 2 chart coordinates only, with its exact Jacobian (including
``d kd / dx``).  Each evaluation makes two passes over the N lights (N is a
runtime size): the first ``names.SOLVE_TERM_CACHE`` lights' reflectance terms are
kept in a small local matrix between the passes, the later ones evaluated again.

Observation weights ``w_k`` (the (N, H, W) buffer) are 0 for dropped
observations (shadow: grey value below ``shadow_threshold`` times the pixel's
brightest; saturated: a channel >= ``saturation``; or masked out by the
caller's ``valid``) and otherwise 1, times the robust (IRLS) weight of the
Huber or Cauchy loss after each reweighting round.  A *dark* observation
(grey value within ``lit_sigmas`` noise levels of 0: attached or cast shadow,
or as good as) gets ``w_k = -1``: a one-sided term ``1/2 min(0, y - kd a)^2``
that only penalises a model brighter than the observation, i.e. the
inequality ``n.l <= ~0`` of an attached shadow, without letting the clipped
positive noise of a shadowed pixel pull the normal toward the terminator.
It does not enter the albedo's elimination (the albedo is that of the lit
observations, so the reduced cost and its exact Jacobian stay as above).

Specialisation: Warp emits every ``@wp.func`` a kernel reaches, and a kernel
that switched at run time between the solvers, the reflectance models and
the robust losses carried all of them (NVRTC then inlines them at every call
site).  :func:`get_solve_kernels` instead builds, once per
``(method, brdf, robust)``, the kernels in a Warp module of their own from
the functions that :func:`gpps.kernels.solve_methods.solver_funcs` defines with
``wp.static`` conditions: the branches of the other solvers, models and losses
are dropped at code generation, so each module holds only the code its launch
runs.  The other settings (iterations, tolerances, starts, thresholds, ...)
stay run-time fields of :class:`SolverParams`.  The kernels are forward-only
(``enable_backward=False``): nothing differentiates through the solver.

Layout: this module is the entry point (the specialisation cache and the names
the pipeline, the tests and ``perf/`` use); the device code lives beside it by
topic: :mod:`gpps.kernels.solve_common` (tags, structs, small helpers),
:mod:`gpps.kernels.solve_cost` (reflectance terms and the variable-projection
evaluation), :mod:`gpps.kernels.solve_methods` (LM, dog leg, BFGS, multi-start
and IRLS), :mod:`gpps.kernels.solve_neighbours` (the neighbour statistics) and
:mod:`gpps.kernels.solve_kernels` (the kernels of one specialisation).
"""

import warp as wp

from gpps import names
from gpps._check import check_choice

from gpps.kernels.solve_common import (
    BFGS,
    DOGLEG,
    FLAG_ALBEDO_FROM_NEIGHBOURS,
    FLAG_FEW_OBSERVATIONS,
    FLAG_ILL_CONDITIONED,
    FLAG_NOT_CONVERGED,
    FLAG_UNFOUNDED,
    FLAG_WOODHAM_FALLBACK,
    LM,
    NONE,
    ROBUST_CAUCHY,
    ROBUST_HUBER,
    ROBUST_NONE,
    Eval,
    Pixel,
    PixelSolution,
    SolverParams,
    StartResult,
    brightest_half_vector,
    cond_frobenius,
    grey,
    light_gram,
    make_pixel,
    solve22,
    start_normal,
    store_least_squares,
    store_solution,
    transport,
)
from gpps.kernels.solve_kernels import make_kernels, make_lanes_kernel, prelude_for
from gpps.kernels.solve_split import split_kernels_for, split_under_kernels_for
from gpps.kernels.solve_methods import solver_funcs
from gpps.kernels.solve_neighbours import (
    LINEAR_ITERS,
    NEIGHBOUR_MIN_COUNT,
    WEISZFELD_ITERS,
    NeighbourStats,
    is_determined,
    neighbour_stats,
    ring_offset,
)

__all__ = [
    "BFGS", "DOGLEG", "LM", "NONE", "ROBUST_CAUCHY", "ROBUST_HUBER", "ROBUST_NONE",
    "FLAG_ALBEDO_FROM_NEIGHBOURS", "FLAG_FEW_OBSERVATIONS", "FLAG_ILL_CONDITIONED", "FLAG_NOT_CONVERGED",
    "FLAG_UNFOUNDED", "FLAG_WOODHAM_FALLBACK", "LINEAR_ITERS", "NEIGHBOUR_MIN_COUNT", "WEISZFELD_ITERS",
    "Eval", "NeighbourStats", "Pixel", "PixelSolution", "SolverParams", "StartResult",
    "brightest_half_vector", "cond_frobenius", "grey", "is_determined", "light_gram", "make_pixel",
    "neighbour_stats", "ring_offset", "solve22", "start_normal", "store_least_squares", "store_solution",
    "transport", "evaluate", "run_lm", "run_dogleg", "run_bfgs", "run_method", "solve_pixel",
    "METHODS", "BRDFS", "ROBUST", "specialisation_key", "module_name", "get_solve_kernels", "batched_in_solve_module",
    "get_solve_batched_kernel",
    "get_split_kernels", "get_split_under_kernels",
]

METHODS = names.SOLVER_NAMES
BRDFS = names.BRDF_NAMES
ROBUST = names.ROBUST_NAMES

# perf/_bench_kernels.py builds its evaluation functions through this name
_solver_funcs = solver_funcs

# generic (run-time dispatch) functions, for direct use from other kernels (e.g. the tests)
_GENERIC = solver_funcs(None, None, None)
evaluate = _GENERIC.evaluate
run_lm = _GENERIC.run_lm
run_dogleg = _GENERIC.run_dogleg
run_bfgs = _GENERIC.run_bfgs
run_method = _GENERIC.run_method
solve_pixel = _GENERIC.solve_pixel

_KERNELS: dict = {}


def specialisation_key(method, brdf, robust) -> tuple:
    """The normalised ``(method, brdf, robust)`` that :func:`get_solve_kernels` builds for these settings.

    Solver ``"none"`` (Woodham only) uses neither the model nor the loss, so it
    has one build.  ``None`` (any of them): run-time switch (the generic build).
    """
    check_choice("method", method, METHODS, allow_none=True)
    check_choice("brdf", brdf, BRDFS, allow_none=True)
    check_choice("robust", robust, ROBUST, allow_none=True)
    if method == "none":
        brdf, robust = "lambertian", "none"
    return method, brdf, robust


def module_name(method, brdf, robust, cache: int = names.SOLVE_TERM_CACHE) -> str:
    """Name of the Warp module holding the kernels of one specialisation (``cache``: the evaluation's kept lights,
    :func:`term_cache_size`; a suffix ``_c<cache>`` when it is not the default)."""
    method, brdf, robust = specialisation_key(method, brdf, robust)
    tag = "_".join("any" if s is None else s.replace("-", "_") for s in (method, brdf, robust))
    return f"gpps.kernels.solve.{tag}" + cache_suffix(cache)


def cache_suffix(cache: int) -> str:
    """The module-name suffix of a term cache size: ``""`` for the default, else ``"_c<cache>"``."""
    cache = int(cache)
    if cache < 1:
        raise ValueError(f"cache: expected at least 1 light, got {cache}")
    return "" if cache == names.SOLVE_TERM_CACHE else f"_c{cache}"


def term_cache_size(device: str, lights: int) -> int:
    """The lights whose terms the solver's evaluation keeps between its passes, for a solve of ``lights``
    images on ``device`` (:func:`gpps.kernels.solve_cost.evaluate_for`).

    CUDA: ``names.SOLVE_TERM_CACHE`` (a thread's local matrix: more would only cost local memory and zeroing on
    launches whose threads already wait on their slowest pixel).  CPU: the smallest of
    ``names.SOLVE_TERM_CACHE_CPU`` that holds every light, the largest beyond it (later lights are evaluated
    twice).  The results do not depend on it: the kept terms are the values a second evaluation gives.
    """
    lights = int(lights)
    if lights < 1:
        raise ValueError(f"lights: expected at least 1 image, got {lights}")
    if not str(device).startswith("cpu"):
        return names.SOLVE_TERM_CACHE
    tiers = names.SOLVE_TERM_CACHE_CPU
    return next((t for t in tiers if t >= lights), tiers[-1])


_LANES: dict = {}


def get_solve_kernel_lanes(method, brdf, robust="none"):
    """The lights-parallel solve kernel (one block of lanes a pixel, launched tiled;
    :func:`gpps.kernels.solve_kernels.solve_kernel_for` with ``lanes``) of one nonlinear solver, reflectance model and
    robust loss, in a Warp module of its own (:func:`module_name` + ``"_lanes"``), built once and cached."""
    key = specialisation_key(method, brdf, robust)
    if None in key or key[0] == "none":
        raise ValueError(f"method, brdf, robust: expected a nonlinear solver and fixed choices, got {key}")
    k = _LANES.get(key)
    if k is None:
        name = module_name(*key) + "_lanes"
        k = make_lanes_kernel(*key, module_name=name, sfx="__" + name.rsplit(".", 1)[1])
        _LANES[key] = k
    return k


_SPLIT: dict = {}


def _split_module(method, brdf, robust, suffix: str, max_registers: int, build):
    """The kernels ``build(funcs, module, sfx)`` makes in the Warp module :func:`module_name` + ``suffix`` of one
    nonlinear solver, reflectance model and robust loss, compiled on CUDA with ``max_registers`` (the CPU build
    ignores it); built once and cached."""
    key = specialisation_key(method, brdf, robust)
    if None in key or key[0] == "none":
        raise ValueError(f"method, brdf, robust: expected a nonlinear solver and fixed choices, got {key}")
    k = _SPLIT.get((key, suffix))
    if k is None:
        name = module_name(*key) + suffix
        sfx = "__" + name.rsplit(".", 1)[1]
        module = wp.get_module(name)
        module.options["cuda_max_registers"] = int(max_registers)
        k = build(solver_funcs(*key, module, sfx), module, sfx)
        _SPLIT[(key, suffix)] = k
    return k


def get_split_kernels(method, brdf, robust="none"):
    """The starts-parallel kernels (:mod:`gpps.kernels.solve_split`) of one nonlinear solver, reflectance model
    and robust loss, in a Warp module of their own (:func:`module_name` + ``"_split"``), built once and cached."""
    return _split_module(method, brdf, robust, "_split", names.SPLIT_SOLVE_MAX_REGISTERS,
                         lambda f, module, sfx: split_kernels_for(prelude_for(module, sfx), f.one_start,
                                                                  f.finish_pixel, module, sfx))


def get_split_under_kernels(method, brdf, robust="none"):
    """The starts-parallel neighbour pass (:func:`gpps.kernels.solve_split.split_under_kernels_for`) of one
    nonlinear solver, reflectance model and robust loss, in a Warp module of its own (:func:`module_name` +
    ``"_split_under"``: built, and compiled, only where the pass runs), with the register cap
    :data:`gpps.names.SPLIT_UNDER_MAX_REGISTERS`."""
    return _split_module(method, brdf, robust, "_split_under", names.SPLIT_UNDER_MAX_REGISTERS,
                         lambda f, module, sfx: split_under_kernels_for(f.one_start, f.finish_pixel, f.held_dark_refit,
                                                                        module, sfx))


def batched_in_solve_module(device) -> bool:
    """Whether, on ``device``, the material scorer's batched kernel (one thread a (candidate, pixel) pair,
    :func:`gpps.kernels.solve_batched.get_batched_kernel`) is built in the solve kernels' module of its
    specialisation (:func:`get_solve_kernels` with ``with_batched``) rather than in a module of its own.

    CPU: yes.  Its compiler builds a module's device functions once and every kernel calls them, so the batched
    kernel adds about 0.5 s to a solve module's 5-6 s, against 3.2-4 s for a module of its own (plastic and
    conductor, LM with the Cauchy loss, 128 kept lights, the 2-core development CPU: ``perf/results/s43``); and the
    model a material comparison chooses has its whole-image solve compiled with its scorer, before the choice.
    CUDA: no.  NVRTC inlines the functions into every kernel, so a merged module costs the sum of its kernels'
    compiles, in one piece, where two modules compile side by side on a first run's helper threads
    (:mod:`gpps.pipeline.prefetch`).
    """
    return str(device).startswith("cpu")


def _kernels_of(method, brdf, robust, cache: int, with_batched: bool) -> tuple:
    """``((solve, underdetermined, smooth), batched)``: :func:`gpps.kernels.solve_kernels.make_kernels`'s four kernels
    for one normalised specialisation, built
    once per ``(key, cache, with_batched)`` and cached; with ``with_batched`` in a module of its own
    (:func:`module_name` + ``"_with_batched"``)."""
    key = specialisation_key(method, brdf, robust)
    cache = int(cache) if key[0] != "none" else names.SOLVE_TERM_CACHE  # (least squares evaluates no model)
    with_batched = bool(with_batched) and key[0] != "none"  # (solver "none" has no material to score)
    ks = _KERNELS.get((key, cache, with_batched))
    if ks is None:
        name = module_name(*key, cache=cache) + ("_with_batched" if with_batched else "")
        ks = make_kernels(*key, module_name=name, sfx="__" + name.rsplit(".", 1)[1], cache=cache,
                          with_batched=with_batched)
        ks = (ks[:3], ks[3])  # (the three as one tuple, the same object at every call)
        _KERNELS[(key, cache, with_batched)] = ks
    return ks


def get_solve_kernels(method, brdf, robust="none", cache: int = names.SOLVE_TERM_CACHE, with_batched: bool = False):
    """``(solve_kernel, underdetermined_kernel, smooth_kernel)`` specialised for one solver, reflectance model and robust loss.

    Args:
        method: ``"none"``, ``"lm"``, ``"dogleg"`` or ``"bfgs"`` (None: run-time ``prm.method``).
        brdf: a :data:`gpps.material.BRDF_NAMES` name (None: run-time ``mat.model``).
        robust: ``"none"``, ``"huber"`` or ``"cauchy"`` (None: run-time ``prm.robust``);
            ``"none"`` emits no IRLS round (``prm.irls_rounds`` must be 0).
        cache: the lights the evaluation keeps between its passes (:func:`term_cache_size`).
        with_batched: the build whose module also holds the material scorer's batched kernel
            (:func:`batched_in_solve_module`; :func:`get_solve_batched_kernel` returns it).  The same kernels
            otherwise, in another module (:func:`module_name` + ``"_with_batched"``); ignored for ``"none"``.

    The kernels are built once per normalised key (:func:`specialisation_key`), cache and ``with_batched`` and
    cached; each build lives in its own Warp module (:func:`module_name`), compiled on first launch or by
    ``wp.load_module``.  ``underdetermined_kernel`` is None for ``method="none"``, and so is ``smooth_kernel``.
    ``prm.method`` / ``mat.model`` / ``prm.robust`` must agree with the specialisation
    (:class:`gpps.pipeline.solver.PixelSolver` sees to it).
    """
    return _kernels_of(method, brdf, robust, cache, with_batched)[0]


def get_solve_batched_kernel(method, brdf, robust="none", cache: int = names.SOLVE_TERM_CACHE):
    """The material scorer's batched kernel (:func:`gpps.kernels.solve_batched.batched_kernel_for`, the
    pixels-parallel build) in the module of :func:`get_solve_kernels` with ``with_batched``: one nonlinear solver,
    reflectance model and robust loss."""
    key = specialisation_key(method, brdf, robust)
    if None in key or key[0] == "none":
        raise ValueError(f"method, brdf, robust: expected a nonlinear solver and fixed choices, got {key}")
    return _kernels_of(*key, cache, True)[1]


def __getattr__(name):
    # the former monolithic kernels: the generic build (run-time switches), made on first access
    if name == "solve_kernel":
        return get_solve_kernels(None, None, None)[0]
    if name == "smooth_kernel":
        return get_solve_kernels(None, None, None)[2]
    if name == "underdetermined_kernel":
        return get_solve_kernels(None, None, None)[1]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""The multigrid PCG's launch forms: one Taichi launch an iteration, one launch per step and level, and the whole
solve in one persistent task.

``IntegratorConfig.launch="fused"`` runs a PCG iteration (cg_step, the V-cycle over every level,
cg_direction) as one kernel, :func:`gpps.kernels.poisson.pcg_iteration`, and the start as another; it
composes the same ti.funcs as the per-level kernels, in the same order, with the level layout compiled
in.  So both launch forms must stop after the same iterations with the same depth: bitwise on the
CPU's build as seen so far, asserted within 1e-12 of the range in float64 and float32 rounding of the
range in float32 (the CPU's parallel ``sc[K] +=`` sums may add their float64 terms in another order from
run to run); on CUDA within the float64 reordering of the block sums' atomics (as
tests/test_integration_cg_sums.py).  The problems cover both cameras, uniform and n_z^2 weights, both
precisions, a mask with holes and three components on a size whose levels halve unevenly (75 x 101 ->
38 x 51 -> 19 x 26 -> 10 x 13 -> 5 x 7), the iteration cap between two residual checks, a warm start
that is already converged, and a mask so small that it is its own coarsest level (no V-cycle levels).

``launch="persistent"`` (:mod:`gpps.kernels.poisson_persistent`; ``"auto"`` on CUDA) runs the start, every
iteration and the stopping test in one task whose phases meet at grid barriers; off CUDA it runs as one thread.
Its arithmetic is the fused launch's through the same per-point funcs; only the order of the float64 sums differs
(strided over the threads and tree-reduced per block, or in pixel order on one thread), so it is held to the same
iterations and to the CUDA tolerance of the fused form against the per-level one, on the same problems.
"""

import numpy as np
import pytest
from scipy import ndimage

from gpps.camera import Orthographic, Perspective
from gpps.host.poisson import level_shapes
from gpps.pipeline.integration import Integrator, IntegratorConfig

H, W = 75, 101


def _problem(camera: str, h: int = H, w: int = W):
    """A smooth height field over a mask with two holes and three components; two NaN normals.

    Returns mask (h, w) bool, normals (h, w, 3) float64, camera."""
    ii, jj = np.meshgrid(np.arange(h, dtype=float), np.arange(w, dtype=float), indexing="ij")
    s = min(h, w) / 75
    mask = np.hypot(ii - 0.45 * h, jj - 0.4 * w) < 30 * s
    mask &= np.hypot(ii - 0.4 * h, jj - 0.33 * w) > 5 * s  # holes
    mask &= np.hypot(ii - 0.55 * h, jj - 0.5 * w) > 4 * s
    mask |= np.hypot(ii - 0.8 * h, jj - 0.85 * w) < 9 * s  # more components
    mask |= (ii > 0.05 * h) & (ii < 0.25 * h) & (jj > 0.75 * w) & (jj < 0.95 * w)
    x, y = (jj - w / 2) / w, -(ii - h / 2) / h
    g = 0.3 * np.exp(-((x + 0.1) ** 2 + (y - 0.05) ** 2) / 0.05) - 0.2 * np.exp(-((x - 0.2) ** 2 + y ** 2) / 0.02)
    n = np.stack([-np.gradient(g, axis=1) * w, np.gradient(g, axis=0) * h, np.ones_like(g)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[int(0.45 * h), int(0.2 * w)] = np.nan  # dropped by the stage
    n[int(0.6 * h), int(0.45 * w)] = np.nan
    if camera == "perspective":
        f = 3.0 * w
        cam = Perspective(np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]]))
    else:
        cam = Orthographic(1.0 / w)
    return mask, n, cam


def _run(device, camera, launch, normals=None, warm=None, shape=(H, W), **kw):
    mask, n, cam = _problem(camera, *shape)
    integ = Integrator(mask, cam, IntegratorConfig(launch=launch, **kw), device=device)
    try:
        return integ.run(n if normals is None else normals, warm, reference_depth=10.0)
    finally:
        integ.close()


def _close(device, dtype):
    """Largest depth difference between the launch forms, in units of the depth range."""
    if device.startswith("cuda"):
        return 1e-9 if dtype == "float64" else 2e-5
    return 1e-12 if dtype == "float64" else 1e-6


def _same(a, b, device, dtype):
    m = a.mask
    assert np.array_equal(a.mask, b.mask)
    assert a.iterations == b.iterations, (a.iterations, b.iterations)
    assert a.converged == b.converged
    rng = float(np.ptp(a.depth[m]))
    assert np.max(np.abs(a.depth[m] - b.depth[m])) <= _close(device, dtype) * rng
    if device == "cpu" and dtype == "float64":
        assert a.solver_residual == pytest.approx(b.solver_residual, rel=1e-6)


def test_problem_is_uneven_with_holes_and_components():
    mask, n, _ = _problem("perspective")
    valid = mask & np.isfinite(n).all(-1)
    assert ndimage.label(valid)[1] == 3
    assert ndimage.label(~valid)[1] >= 3  # outside and two holes
    shapes = level_shapes(H, W, 8)
    assert len(shapes) == 5 and any(h % 2 or w % 2 for h, w in shapes[:-1])


@pytest.mark.parametrize("camera", ["perspective", "orthographic"])
@pytest.mark.parametrize("weighting", ["uniform", "normal"])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_fused_equals_per_level(device, camera, weighting, dtype):
    tol = 1e-10 if dtype == "float64" else 1e-5
    kw = dict(solver="multigrid", weighting=weighting, dtype=dtype, tol=tol)
    fused = _run(device, camera, "fused", **kw)
    per = _run(device, camera, "per-level", **kw)
    _same(fused, per, device, dtype)
    assert fused.iterations >= 4  # a real solve, several residual checks
    if dtype == "float64":
        assert fused.converged and fused.solver_residual <= tol
        # and it is the system's solution: the direct solve's depth
        ref = _run(device, camera, "fused", solver="direct", weighting=weighting)
        m = ref.mask
        assert np.max(np.abs(fused.depth[m] - ref.depth[m])) <= 1e-7 * float(np.ptp(ref.depth[m]))


@pytest.mark.parametrize("check_every", [1, 3])
def test_fused_stops_at_the_cap_between_checks(device, check_every):
    """max_iter 7 with a check every 3 iterations: both forms stop at the cap with the same depth."""
    kw = dict(weighting="normal", dtype="float64", tol=1e-14, max_iter=7, check_every=check_every)
    fused = _run(device, "perspective", "fused", **kw)
    per = _run(device, "perspective", "per-level", **kw)
    assert fused.iterations == per.iterations == 7 and not fused.converged
    _same(fused, per, device, "float64")


def test_fused_converged_warm_start(device):
    """A warm start at the solution (its float32 depth): the start launch's residual is already below a
    tol of 1e-2, no iteration, in both forms."""
    kw = dict(weighting="uniform", dtype="float64")
    first = _run(device, "perspective", "fused", tol=1e-8, **kw)
    for launch in ("fused", "per-level"):
        again = _run(device, "perspective", launch, warm=first.depth, tol=1e-2, **kw)
        assert again.iterations == 0 and again.converged
        m = first.mask
        assert np.max(np.abs(again.depth[m] - first.depth[m])) <= 1e-6 * float(np.ptp(first.depth[m]))


def test_fused_single_level(device):
    """A 6 x 7 map is its own coarsest level: the V-cycle is the exact coarse solve alone."""
    assert len(level_shapes(6, 7, 8)) == 1
    kw = dict(weighting="normal", dtype="float64", tol=1e-10)
    mask, n, cam = _problem("orthographic", 6, 7)
    mask = np.ones((6, 7), bool)
    n = np.where(np.isfinite(n), n, np.array([0.0, 0.0, 1.0]))
    res = {}
    for launch in ("fused", "per-level"):
        integ = Integrator(mask, cam, IntegratorConfig(launch=launch, **kw), device=device)
        try:
            res[launch] = integ.run(n)
        finally:
            integ.close()
    _same(res["fused"], res["per-level"], device, "float64")
    assert res["fused"].converged and res["fused"].iterations <= 2  # the exact preconditioner


def test_fused_reuses_the_stage_across_calls(device):
    """A stream of calls on one stage (the fields and compiled kernels reused) gives the first call's depth."""
    mask, n, cam = _problem("perspective")
    integ = Integrator(mask, cam, IntegratorConfig(weighting="normal", dtype="float64", tol=1e-10), device=device)
    try:
        a, b = integ.run(n), integ.run(n)
    finally:
        integ.close()
    _same(a, b, device, "float64")


def test_launch_is_checked():
    assert IntegratorConfig().launch == "fused"
    with pytest.raises(ValueError, match="launch"):
        IntegratorConfig(launch="graph")
    with pytest.raises(ValueError, match="persistent_blocks"):
        IntegratorConfig(persistent_blocks=0)


def _close_persistent(dtype):
    """Largest depth difference of the persistent form against the fused one, in units of the depth range: the
    float64 dot products are added in another order on every device (the fused form's CUDA tolerance)."""
    return 1e-9 if dtype == "float64" else 2e-5


def _same_persistent(a, b, dtype):
    m = a.mask
    assert np.array_equal(a.mask, b.mask)
    assert a.iterations == b.iterations, (a.iterations, b.iterations)
    assert a.converged == b.converged
    rng = float(np.ptp(a.depth[m]))
    assert np.max(np.abs(a.depth[m] - b.depth[m])) <= _close_persistent(dtype) * rng
    if dtype == "float64":
        assert a.solver_residual == pytest.approx(b.solver_residual, rel=1e-6)


@pytest.mark.parametrize("camera", ["perspective", "orthographic"])
@pytest.mark.parametrize("weighting", ["uniform", "normal"])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_persistent_equals_fused(device, camera, weighting, dtype):
    tol = 1e-10 if dtype == "float64" else 1e-5
    kw = dict(solver="multigrid", weighting=weighting, dtype=dtype, tol=tol)
    pers = _run(device, camera, "persistent", **kw)
    fused = _run(device, camera, "fused", **kw)
    _same_persistent(pers, fused, dtype)
    assert pers.iterations >= 4
    assert pers.converged and pers.solver_residual <= tol


@pytest.mark.parametrize("check_every", [1, 3])
def test_persistent_stops_at_the_cap_between_checks(device, check_every):
    """max_iter 7 with a check every 3 iterations: the persistent task stops at the cap as the host loop does."""
    kw = dict(weighting="normal", dtype="float64", tol=1e-14, max_iter=7, check_every=check_every)
    pers = _run(device, "perspective", "persistent", **kw)
    fused = _run(device, "perspective", "fused", **kw)
    assert pers.iterations == fused.iterations == 7 and not pers.converged
    _same_persistent(pers, fused, "float64")


def test_persistent_converged_warm_start(device):
    """A warm start at the solution: no iteration, the start's depth back."""
    kw = dict(weighting="uniform", dtype="float64")
    first = _run(device, "perspective", "fused", tol=1e-8, **kw)
    again = _run(device, "perspective", "persistent", warm=first.depth, tol=1e-2, **kw)
    assert again.iterations == 0 and again.converged
    m = first.mask
    assert np.max(np.abs(again.depth[m] - first.depth[m])) <= 1e-6 * float(np.ptp(first.depth[m]))


def test_persistent_single_level(device):
    """A 6 x 7 map is its own coarsest level: the persistent V-cycle is the exact coarse solve alone."""
    kw = dict(weighting="normal", dtype="float64", tol=1e-10)
    mask, n, cam = _problem("orthographic", 6, 7)
    mask = np.ones((6, 7), bool)
    n = np.where(np.isfinite(n), n, np.array([0.0, 0.0, 1.0]))
    res = {}
    for launch in ("persistent", "fused"):
        integ = Integrator(mask, cam, IntegratorConfig(launch=launch, **kw), device=device)
        try:
            res[launch] = integ.run(n)
        finally:
            integ.close()
    _same_persistent(res["persistent"], res["fused"], "float64")
    assert res["persistent"].converged and res["persistent"].iterations <= 2


def test_persistent_kernel_kept_across_calls(device):
    """Calls on one stage reuse the persistent kernel built at the first (one build per geometry and grid) and
    give the first call's depth."""
    mask, n, cam = _problem("perspective")
    cfg = IntegratorConfig(weighting="normal", dtype="float64", tol=1e-10, launch="persistent")
    integ = Integrator(mask, cam, cfg, device=device)
    try:
        a, b = integ.run(n), integ.run(n)
        assert len(integ._dev["persistent"]) == 1
    finally:
        integ.close()
    _same_persistent(a, b, "float64")

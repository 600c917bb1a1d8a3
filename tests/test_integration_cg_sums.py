"""The multigrid PCG's block-sum build (CUDA) against its per-pixel-atomic build and the direct solve.

``IntegratorConfig.cg_sums`` picks how the CG's float64 dot products are summed on the device
(:mod:`gpps.kernels.poisson`): ``"block"`` (tree sums per CUDA block in shared memory, one atomic a
block; the CUDA default) or ``"atomic"`` (``sc[K] +=`` per pixel; the CPU build, and CUDA's before the
block sums).  Both run the same CG: the same per-pixel arithmetic, float64 terms, alpha/beta rules and
masks; only the order of the float64 additions differs (and CUDA's atomics have no fixed order anyway).
So on a problem that exercises every branch (perspective, BiNI's n_z^2 edge weights and the uniform
device right-hand side, a mask with holes and two components, dropped NaN normals, a pixel count that
is not a multiple of the block) the two builds must give the same depth to a tight tolerance and the
same iteration count, and both the direct solve's depth.

Taichi's CPU backend has no shared arrays (``ti.simt.block.sync`` raises "not supported for arch x64"),
so the block build exists on CUDA only: on the CPU this file checks that asking for it is a clear error.
"""

import numpy as np
import pytest

from gpps.camera import Perspective
from gpps.kernels.block_sum import BLOCK
from gpps.pipeline.integration import Integrator, IntegratorConfig

H, W = 150, 173  # h * w = 25950, not a multiple of BLOCK: the last block of every loop has padding threads


def _problem():
    """Perspective bumps on a disc with two holes and a detached blob; a few NaN normals.

    Returns mask (H, W) bool, normals (H, W, 3) float64, camera."""
    ii, jj = np.meshgrid(np.arange(H, dtype=float), np.arange(W, dtype=float), indexing="ij")
    mask = np.hypot(ii - 70, jj - 80) < 62
    mask &= np.hypot(ii - 55, jj - 60) > 9  # holes
    mask &= np.hypot(ii - 95, jj - 105) > 6
    mask |= np.hypot(ii - 130, jj - 155) < 12  # a second component
    fx = fy = 300.0
    cx, cy = (W - 1) / 2, (H - 1) / 2
    x, y = (jj - cx) / W, -(ii - cy) / H
    # a smooth height field z = g(x, y) seen in the gpps frame: normal ~ (-g_x, -g_y, 1)
    g = 0.3 * np.exp(-((x + 0.1) ** 2 + (y - 0.05) ** 2) / 0.05) - 0.2 * np.exp(-((x - 0.2) ** 2 + (y + 0.2) ** 2) / 0.02)
    gx = np.gradient(g, axis=1) * W
    gy = -np.gradient(g, axis=0) * H
    n = np.stack([-gx, -gy, np.ones_like(g)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[40, 70] = np.nan  # dropped from the mask by the stage
    n[100, 60] = np.nan
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return mask, n, Perspective(K)


def test_problem_exercises_the_padding_and_holes():
    mask, n, _ = _problem()
    valid = mask & np.isfinite(n).all(-1)
    from scipy import ndimage

    assert (H * W) % BLOCK != 0 and valid.sum() % BLOCK != 0
    assert ndimage.label(valid)[1] == 2
    assert ndimage.label(~valid)[1] >= 3  # the outside and two holes (and the NaN pixels)


def _run(device, cg_sums, **kw):
    mask, n, cam = _problem()
    integ = Integrator(mask, cam, IntegratorConfig(cg_sums=cg_sums, **kw), device=device)
    try:
        return integ.run(n, reference_depth=10.0)
    finally:
        integ.close()


@pytest.mark.parametrize("weighting", ["uniform", "normal"])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_block_sums_match_atomic_sums_and_direct(device, dtype, weighting):
    if not device.startswith("cuda"):
        pytest.skip("the block-sum build is CUDA-only: Taichi's CPU backend has no shared arrays "
                    "(ti.simt.block.sync: 'not supported for arch x64'); the CPU runs the atomic build")
    tol = 1e-10 if dtype == "float64" else 1e-5
    kw = dict(solver="multigrid", weighting=weighting, dtype=dtype, tol=tol)
    blk = _run(device, "block", **kw)
    atm = _run(device, "atomic", **kw)
    auto = _run(device, "auto", **kw)
    ref = _run(device, "auto", solver="direct", weighting=weighting)
    m = ref.mask
    assert m.sum() % BLOCK != 0 and blk.n_invalid == 2
    assert np.array_equal(blk.mask, m) and np.array_equal(atm.mask, m)
    rng = float(np.ptp(ref.depth[m]))
    # same CG, float64 sums in another order: the same iteration count (the residual is read every
    # check_every iterations, so a count can only differ if a check lands within rounding of tol: not here)
    assert blk.iterations == atm.iterations == auto.iterations, (blk.iterations, atm.iterations, auto.iterations)
    # float64 reaches tol; float32 may stop at its precision floor (the stagnation rule), the same
    # way in both builds (seen on an H100: uniform weights, relative residual 5.4e-5 for tol 1e-5)
    assert blk.converged == atm.converged
    if dtype == "float64":
        assert blk.converged
    close = 1e-9 if dtype == "float64" else 2e-5
    assert np.max(np.abs(blk.depth[m] - atm.depth[m])) <= close * rng
    assert np.max(np.abs(auto.depth[m] - blk.depth[m])) <= close * rng
    # and both solve the system: the direct solve's depth
    assert np.max(np.abs(blk.depth[m] - ref.depth[m])) <= (1e-7 if dtype == "float64" else 1e-4) * rng
    floor = tol if dtype == "float64" else 1e-4
    assert blk.solver_residual <= floor
    assert abs(blk.solver_residual - atm.solver_residual) <= 1e-3 * max(blk.solver_residual, tol)


def test_block_sums_in_the_jacobi_residual(device):
    """The Jacobi solver's residual checks use residual_norm's sums: the same sweeps, the same residual."""
    if not device.startswith("cuda"):
        pytest.skip("the block-sum build is CUDA-only (Taichi's CPU backend has no shared arrays)")
    kw = dict(solver="jacobi", weighting="normal", dtype="float64", max_iter=256, tol=1e-9)
    blk, atm = _run(device, "block", **kw), _run(device, "atomic", **kw)
    assert blk.iterations == atm.iterations == 256
    assert blk.solver_residual == pytest.approx(atm.solver_residual, rel=1e-12)
    m = blk.mask
    assert np.max(np.abs(blk.depth[m] - atm.depth[m])) <= 1e-12 * float(np.ptp(blk.depth[m]))


def test_block_sums_need_cuda(device):
    if device.startswith("cuda"):
        pytest.skip("checks the CPU's refusal of the CUDA-only block build")
    with pytest.raises(ValueError, match="cg_sums"):
        _run(device, "block")
    # the CPU's default is the atomic build, which solves the problem
    res = _run(device, "auto", dtype="float64", tol=1e-10)
    assert res.converged and res.n_invalid == 2


def test_cg_sums_is_checked():
    with pytest.raises(ValueError, match="cg_sums"):
        IntegratorConfig(cg_sums="warp")

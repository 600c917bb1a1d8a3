"""Kernels used only by perf/bench.py: one residual + Jacobian evaluation per pixel, a FLOP-peak probe."""

import warp as wp

from gpps.kernels import solve as sk
from gpps.kernels.brdf import CameraParams, LightParams, MaterialParams
from gpps.kernels.jacobians import tangent_basis_t1

_MOD = wp.get_module("perf_bench_kernels")
_F = sk._solver_funcs("lm", "blinn-phong", "none", _MOD, "__bench_bp")
evaluate_bp = _F.evaluate


@wp.kernel(module=_MOD, enable_backward=False)
def evaluate_kernel(
    images: wp.array3d(dtype=wp.vec3),
    weights: wp.array3d(dtype=wp.float32),
    depth: wp.array2d(dtype=wp.float32),
    normals: wp.array2d(dtype=wp.vec3),
    cam: CameraParams,
    lights: LightParams,
    mat: MaterialParams,
    prm: sk.SolverParams,
    cost: wp.array2d(dtype=wp.float32),
):
    """Reduced cost, J^T r and J^T J of the Blinn-Phong model at each pixel's normal (one evaluation)."""
    i, j = wp.tid()
    px = sk.make_pixel(cam, depth, i, j, prm)
    n0 = normals[i, j]
    t1 = tangent_basis_t1(n0)
    t2 = wp.cross(n0, t1)
    ev = evaluate_bp(n0, t1, t2, wp.vec2(0.0), images, weights, px, lights, mat)
    cost[i, j] = ev.cost + ev.jtj[0, 1] + ev.jtr[0]


@wp.kernel(enable_backward=False)
def fma_peak(out: wp.array(dtype=wp.float32), n: int):
    """8 independent FMA chains of n steps per thread: 16 n FLOPs a thread."""
    tid = wp.tid()
    a0 = float(tid) * 1.0e-9
    a1 = a0 + 0.1
    a2 = a0 + 0.2
    a3 = a0 + 0.3
    a4 = a0 + 0.4
    a5 = a0 + 0.5
    a6 = a0 + 0.6
    a7 = a0 + 0.7
    for _ in range(n):
        a0 = a0 * 0.9999 + 1.0e-7
        a1 = a1 * 0.9999 + 1.0e-7
        a2 = a2 * 0.9999 + 1.0e-7
        a3 = a3 * 0.9999 + 1.0e-7
        a4 = a4 * 0.9999 + 1.0e-7
        a5 = a5 * 0.9999 + 1.0e-7
        a6 = a6 * 0.9999 + 1.0e-7
        a7 = a7 * 0.9999 + 1.0e-7
    out[tid] = a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7


@wp.kernel(enable_backward=False)
def fma_peak_f64(out: wp.array(dtype=wp.float64), n: int):
    """fma_peak in float64 (DGMC and BiNI compute in float64): 16 n FLOPs a thread."""
    tid = wp.tid()
    a0 = wp.float64(tid) * wp.float64(1.0e-9)
    a1 = a0 + wp.float64(0.1)
    a2 = a0 + wp.float64(0.2)
    a3 = a0 + wp.float64(0.3)
    a4 = a0 + wp.float64(0.4)
    a5 = a0 + wp.float64(0.5)
    a6 = a0 + wp.float64(0.6)
    a7 = a0 + wp.float64(0.7)
    c = wp.float64(0.9999)
    d = wp.float64(1.0e-7)
    for _ in range(n):
        a0 = a0 * c + d
        a1 = a1 * c + d
        a2 = a2 * c + d
        a3 = a3 * c + d
        a4 = a4 * c + d
        a5 = a5 * c + d
        a6 = a6 * c + d
        a7 = a7 * c + d
    out[tid] = a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7

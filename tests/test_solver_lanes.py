"""PixelSolver's lights-parallel solve (``SolverConfig.parallel="lights"``): one block of 32 lanes a pixel, the
light loops split over the lanes and every sum reduced over the block (gpps.kernels.solve_kernels
``solve_kernel_lanes``), against the one-thread-a-pixel kernel on the same frame.

Reference: the one-thread kernel (itself tested against numpy and finite differences in tests/test_solvers.py).
On one lane (the CPU without ``warp.config.enable_cpu_blocks``) the sums run in the same order and every output
is bitwise equal.  With 32 lanes (CUDA, or the CPU's cooperative blocks) the sums are reordered: float32
rounding of sums of 40 terms carried through the iteration.  Bounds: normals within 0.01 deg on at least 97 %
of the pixels (a last-bit change can move where an iteration stops), residuals within 1e-4 relative + 1e-6 of
the image scale, the flags equal apart from "not converged", which observations count (the weights' signs)
equal, the IRLS weights within 1e-3 relative on 97 %, the condition numbers within 1e-4.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gpps.flows.synthetic import default_lights, render
from gpps.host.scenes import make_scene
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material
from gpps.pipeline.solver import PixelSolver, SolverConfig

NOT_CONVERGED = 4


def _case(light_kind, n=40, size=24, device=None):
    sc = make_scene("sphere", size, "perspective", albedo="texture")
    mat = Material.default_for("cook-torrance")
    L = default_lights(light_kind, n, layout="spiral")
    img = render(sc, mat, L, bits=16, noise=0.01, device=device)
    img = img / np.asarray(L.intensities, np.float32)[:, None, None, :]
    Lu = DirectionalLights(L.directions) if light_kind == "directional" else PointLights(L.positions)
    return img, Lu, sc, mat


def _solve(img, lights, sc, mat, cfg, device, *, depth=None, warm=None):
    s = PixelSolver(img.shape[:3], sc.camera, lights, mat, cfg, device=device)
    s.upload(img, sc.mask, depth=depth, init_normals=warm)
    s.step()
    out = s.fetch(("normals", "albedo", "residual", "iterations", "flags", "weights", "cond"))
    return out, s


@pytest.mark.parametrize("method,robust,light_kind", [("lm", "cauchy", "directional"), ("dogleg", "none", "point"),
                                                      ("bfgs", "huber", "directional")])
@pytest.mark.parametrize("cpu_blocks", [False, True])
def test_lights_parallel_solve_equals_one_thread_a_pixel(method, robust, light_kind, cpu_blocks, device, monkeypatch):
    import warp as wp

    if cpu_blocks:
        if device != "cpu":
            pytest.skip("enable_cpu_blocks concerns the CPU backend")
        monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    img, lights, sc, mat = _case(light_kind, device=device)
    depth = sc.depth if light_kind == "point" else None
    base = SolverConfig(solver=method, robust=robust, irls_rounds=2, shadow_threshold=0.02, starts=3,
                        neighbour_radius=0)
    scale = float(np.percentile(img[:, sc.mask].mean(-1), 99))
    for warm in (None, sc.normals.astype(np.float32)):
        cfg = replace(base, warm_start=warm is not None)
        a, sa = _solve(img, lights, sc, mat, replace(cfg, parallel="pixels"), device, depth=depth, warm=warm)
        b, sb = _solve(img, lights, sc, mat, replace(cfg, parallel="lights"), device, depth=depth, warm=warm)
        assert not sa._uses_lanes() and sb._uses_lanes()
        m = sc.mask
        if device == "cpu" and not cpu_blocks:
            for k in a:
                np.testing.assert_array_equal(a[k], b[k], err_msg=k)
            continue
        # which observations count (dropped 0, dark < 0, lit > 0) is decided per light: equal; the IRLS
        # weights are functions of the solution (float rounding)
        np.testing.assert_array_equal(np.sign(a["weights"]), np.sign(b["weights"]))
        close = np.abs(a["weights"] - b["weights"]) <= 1e-3 * np.abs(a["weights"])
        assert np.mean(close) >= 0.97
        np.testing.assert_allclose(b["cond"][m], a["cond"][m], rtol=1e-4)
        na, nb = a["normals"][m].astype(np.float64), b["normals"][m].astype(np.float64)
        ang = np.degrees(2.0 * np.arcsin(np.linalg.norm(na - nb, axis=-1) / 2.0))
        assert np.mean(ang < 1e-2) >= 0.97, np.sort(ang)[-10:]
        assert np.all(np.abs(a["residual"][m] - b["residual"][m]) <= 1e-4 * a["residual"][m] + 1e-6 * scale) or \
            np.mean(np.abs(a["residual"][m] - b["residual"][m]) <= 1e-4 * a["residual"][m] + 1e-6 * scale) >= 0.97
        np.testing.assert_array_equal(a["flags"][m] & ~NOT_CONVERGED, b["flags"][m] & ~NOT_CONVERGED)
        assert np.all(b["normals"][~m] == 0)


def test_parallel_auto_choice(device):
    """"auto": the lanes only on CUDA, from LIGHTS_PARALLEL_MIN images, for solves of at most
    LIGHTS_PARALLEL_PAIRS_PER_IMAGE x N mask pixels; never for the least-squares solver."""
    from gpps.names import LIGHTS_PARALLEL_MIN, LIGHTS_PARALLEL_PAIRS_PER_IMAGE

    img, lights, sc, mat = _case("directional", n=LIGHTS_PARALLEL_MIN, size=16, device=device)
    s = PixelSolver(img.shape[:3], sc.camera, lights, mat, SolverConfig(), device=device)
    s.upload(img, sc.mask)
    assert s._uses_lanes() == device.startswith("cuda")
    big = np.ones(sc.mask.shape, bool)
    if big.sum() > LIGHTS_PARALLEL_PAIRS_PER_IMAGE * LIGHTS_PARALLEL_MIN:
        s.set_mask(big)
        assert not s._uses_lanes()
    s.set_config(SolverConfig(solver="none", parallel="lights"))
    assert not s._uses_lanes()
    with pytest.raises(ValueError, match="parallel"):
        SolverConfig(parallel="threads")


@pytest.mark.parametrize("cpu_blocks", [False, True])
def test_lights_parallel_degenerate_pixels(cpu_blocks, device, monkeypatch):
    """Pixels the lanes must treat exactly as one thread does: nothing lit (all zeros), everything saturated,
    only two observations left by ``valid``, and lanes beyond the light count (20 lights on 32 lanes: lanes
    20-31 hold no light).  Flags, weights and cond must agree; the determined pixels' normals as above."""
    import warp as wp

    if cpu_blocks:
        if device != "cpu":
            pytest.skip("enable_cpu_blocks concerns the CPU backend")
        monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    img, lights, sc, mat = _case("directional", n=20, size=16, device=device)
    img = np.array(img, np.float32)
    ii, jj = np.nonzero(sc.mask)
    dark, sat, two = (ii[5], jj[5]), (ii[40], jj[40]), (ii[80], jj[80])
    img[:, dark[0], dark[1]] = 0.0
    img[:, sat[0], sat[1]] = 10.0
    valid = np.ones(img.shape[:3], bool)
    valid[2:, two[0], two[1]] = False
    cfg = SolverConfig(solver="lm", robust="cauchy", irls_rounds=2, starts=3, saturation=5.0, neighbour_radius=0)
    outs = []
    for par in ("pixels", "lights"):
        s = PixelSolver(img.shape[:3], sc.camera, lights, mat, replace(cfg, parallel=par), device=device)
        s.upload(img, sc.mask, valid=valid)
        s.step()
        outs.append(s.fetch(("normals", "albedo", "residual", "iterations", "flags", "weights", "cond")))
    a, b = outs
    m = sc.mask
    for px in (dark, sat, two):
        assert a["flags"][px] == b["flags"][px] and a["flags"][px] & 2  # few observations, both ways
        np.testing.assert_array_equal(np.sign(a["weights"][:, px[0], px[1]]), np.sign(b["weights"][:, px[0], px[1]]))
        assert np.all(np.isfinite(b["normals"][px])) and np.isfinite(b["residual"][px])
    if device == "cpu" and not cpu_blocks:
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        return
    np.testing.assert_array_equal(a["flags"][m] & ~NOT_CONVERGED, b["flags"][m] & ~NOT_CONVERGED)
    ok = m & ((a["flags"] & 2) == 0)
    na, nb = a["normals"][ok].astype(np.float64), b["normals"][ok].astype(np.float64)
    ang = np.degrees(2.0 * np.arcsin(np.linalg.norm(na - nb, axis=-1) / 2.0))
    assert np.mean(ang < 1e-2) >= 0.97

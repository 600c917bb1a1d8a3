"""The starts-parallel whole-image solve (gpps.kernels.solve_split, SolverConfig.split_starts) against the
one-kernel solve: bitwise on the CPU (the same functions, the same order), to float rounding on CUDA."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from cases import make_case

from gpps.names import FLAG_NOT_CONVERGED
from gpps.pipeline.solver import PixelSolver, SolverConfig

CASES = [("bumps", "perspective", "directional", "cook-torrance", "none", 0),
         ("sphere", "orthographic", "point", "blinn-phong", "cauchy", 2)]


def _assert_same_solve(a, b, sel, device):
    """The one-kernel (``a``) and starts-parallel (``b``) outputs agree: bit for bit on the CPU; on CUDA to
    another module's rounding over the pixels ``sel``: a 3-image fit's starts may end in other minima of about
    equal cost, whose run may or may not hit the iteration cap (FLAG_NOT_CONVERGED differed on an H100); the
    prelude's flags (observations, conditioning, Woodham fallback) are the same."""
    if device.startswith("cuda"):
        keep = ~np.int32(FLAG_NOT_CONVERGED)
        assert np.array_equal(a["flags"] & keep, b["flags"] & keep)
        assert np.mean((a["flags"] != b["flags"])[sel]) < 0.05
        ra, rb = a["residual"][sel].astype(np.float64), b["residual"][sel].astype(np.float64)
        assert abs(np.mean(ra ** 2) - np.mean(rb ** 2)) <= 1e-3 * np.mean(ra ** 2) + 1e-12
        cos = np.clip(np.sum(a["normals"][sel] * b["normals"][sel], -1), -1.0, 1.0)
        assert np.median(np.degrees(np.arccos(cos))) < 1e-3
    else:
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.parametrize("scene,camera,light_kind,brdf,robust,irls", CASES)
def test_split_starts_equal_one_kernel(scene, camera, light_kind, brdf, robust, irls, device):
    img, lights, sc, mat = make_case(scene, 40, camera, light_kind, brdf, noise=0.01, device=device)
    depth = sc.depth if light_kind == "point" else None
    out = {}
    for split in (False, True):
        cfg = replace(SolverConfig(), robust=robust, irls_rounds=irls, split_starts=split)
        with PixelSolver(img.shape[:3], sc.camera, lights, mat, cfg, device=device) as s:
            assert s._uses_split() is split  # noqa: SLF001
            out[split] = s.run(img, sc.mask, depth=depth)
    _assert_same_solve(out[False], out[True], sc.mask, device)


def test_split_starts_choice(device):
    img, lights, sc, mat = make_case("sphere", 24, "orthographic", "directional", "lambertian", device=device)
    cuda = device.startswith("cuda")
    for cfg, want in ((SolverConfig(), cuda), (replace(SolverConfig(), starts=1), False),
                      (replace(SolverConfig(), warm_start=True), False), (replace(SolverConfig(), solver="none"), False),
                      (replace(SolverConfig(), split_starts=True), True), (replace(SolverConfig(), split_starts=False), False)):
        with PixelSolver(img.shape[:3], sc.camera, lights, mat, cfg, device=device) as s:
            assert s._uses_split() is want, cfg  # noqa: SLF001
    with pytest.raises(TypeError, match="split_starts"):
        SolverConfig(split_starts="yes")


@pytest.mark.parametrize("irls", [0, 2])
def test_split_starts_subset_resolve_equals_one_kernel(irls, device):
    """``step_subset`` with a cold multi-start config and ``split_starts=True`` runs the starts-parallel kernels
    (for subsets of hard pixels, whose one-thread solve of 10 starts sets the launch's time); it equals the
    one-kernel subset solve (bitwise on the CPU) and leaves the other pixels alone."""
    import warp as wp

    img, lights, sc, mat = make_case("bumps", 40, "perspective", "directional", "cook-torrance", noise=0.01,
                                     device=device)
    m = sc.mask
    rng = np.random.default_rng(3)
    sub = m & (rng.random(m.shape) < 0.05)
    base = replace(SolverConfig(), robust="cauchy", irls_rounds=irls)
    out = {}
    for split in (False, True):
        with PixelSolver(img.shape[:3], sc.camera, lights, mat, replace(base, split_starts=False),
                         device=device) as s:
            first = s.run(img, m)
            s.normals.assign(np.where(sub[..., None], 0.0, first["normals"]).astype(np.float32))  # spoilt
            sub_dev = wp.array(sub.astype(np.uint8), device=device)
            cfg = replace(base, starts=10, max_iters=50, split_starts=split)
            assert s._uses_split(cfg) is split  # noqa: SLF001
            s.step_subset(sub_dev, cfg)
            out[split] = s.fetch()
        for k in ("normals", "albedo", "residual", "flags"):  # outside the subset: untouched
            np.testing.assert_array_equal(out[split][k][~sub], first[k][~sub], err_msg=k)
        # re-solved: the cold solve's answer, not the spoilt start's
        assert np.all(np.abs(np.linalg.norm(out[split]["normals"][sub], axis=-1) - 1.0) < 1e-4)
    _assert_same_solve(out[False], out[True], sub, device)


@pytest.mark.parametrize("irls", [0, 2])
def test_split_neighbour_pass_equals_one_kernel(irls, device):
    """The neighbour pass for pixels with fewer than 3 lit observations in its starts-parallel form
    (``split_under_kernels_for``, run with the split solve) equals ``underdetermined_kernel`` (bitwise on the
    CPU): on a sphere under 3 lights its attached-shadow band has 1-2 lit observations a pixel."""
    from gpps.names import FLAG_ALBEDO_FROM_NEIGHBOURS, FLAG_FEW_OBSERVATIONS

    img, lights, sc, mat = make_case("sphere", 40, "orthographic", "directional", "cook-torrance", noise=0.01,
                                     device=device)
    out = {}
    for split in (False, True):
        cfg = replace(SolverConfig(), robust="cauchy", irls_rounds=irls, split_starts=split)
        with PixelSolver(img.shape[:3], sc.camera, lights, mat, cfg, device=device) as s:
            out[split] = s.run(img, sc.mask)
            assert (("underdetermined", split) in s._cmds) and (("underdetermined", not split) not in s._cmds)  # noqa: SLF001
    few = (out[False]["flags"] & FLAG_FEW_OBSERVATIONS) != 0
    held = (out[True]["flags"] & FLAG_ALBEDO_FROM_NEIGHBOURS) != 0
    assert few[sc.mask].sum() >= 20 and held.sum() >= 20, (few.sum(), held.sum())
    _assert_same_solve(out[False], out[True], sc.mask, device)
    # the subset form (step_subset with split_starts=True): re-solves only the subset's under-determined pixels
    import warp as wp

    sub = few & sc.mask & (np.arange(40)[:, None] % 2 == 0)
    res = {}
    for split in (False, True):
        base = replace(SolverConfig(), robust="cauchy", irls_rounds=irls, split_starts=False)
        with PixelSolver(img.shape[:3], sc.camera, lights, mat, base, device=device) as s:
            first = s.run(img, sc.mask)
            s.normals.assign(np.where(sub[..., None], 0.0, first["normals"]).astype(np.float32))
            s.step_subset(wp.array(sub.astype(np.uint8), device=device), replace(base, split_starts=split))
            res[split] = s.fetch()
        for k in ("normals", "albedo", "flags"):
            np.testing.assert_array_equal(res[split][k][~sub], first[k][~sub], err_msg=k)
    assert np.all(res[True]["flags"][sub] & FLAG_ALBEDO_FROM_NEIGHBOURS)
    _assert_same_solve(res[False], res[True], sub, device)

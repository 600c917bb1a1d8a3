"""PixelSolver re-solves of the uploaded frame and the device merge (gpps/kernels/merge.py) against the host rule."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
from cases import make_case

from gpps.host.merge import ranks_better
from gpps.pipeline.solver import PixelSolver, SolverConfig

NAMES = ("normals", "albedo", "residual", "iterations", "flags", "cond")


def test_resolve_and_merge_equal_host_merge(device):
    """A cold solve, a warm re-solve of a subset from other normals and the device merge equal two full
    uploads merged on the host with gpps.host.merge.ranks_better (as RON merged them before)."""
    img, lights, sc, mat = make_case("sphere", 40, "perspective", "directional", "cook-torrance", device=device)
    m = sc.mask
    cold_cfg = SolverConfig(starts=3)
    warm_cfg = replace(cold_cfg, warm_start=True, starts=1, neighbour_radius=0)
    rng = np.random.default_rng(1)
    sub = m & (rng.random(m.shape) < 0.5)
    init = sc.normals.astype(np.float32)  # the truth: the warm solve wins on most pixels
    # host reference: two uploads, merge in numpy
    ref_s = PixelSolver(img.shape[:3], sc.camera, lights, mat, cold_cfg, device=device)
    cold = ref_s.run(img, m)
    ref_s.set_config(warm_cfg)
    warm = ref_s.run(img, sub, init_normals=init)
    better = sub & ranks_better(warm["residual"], warm["flags"], cold["residual"])
    ref = {k: np.where(better.reshape(better.shape + (1,) * (cold[k].ndim - 2)), warm[k], cold[k])
           for k in ("normals", "albedo", "residual", "flags", "cond")}
    ref["iterations"] = cold["iterations"] + np.where(sub, warm["iterations"], 0)
    # device: one upload, re-solve, merge
    s = PixelSolver(img.shape[:3], sc.camera, lights, mat, cold_cfg, device=device)
    s.upload(img, m)
    s.step()
    s.save()
    s.set_config(warm_cfg)
    s.set_mask(sub)
    s.set_start(init)
    s.step()
    s.merge_saved()
    out = s.fetch(NAMES)
    assert better.sum() > 0.2 * sub.sum()
    for k in NAMES:
        np.testing.assert_array_equal(out[k], ref[k], err_msg=k)


def test_set_depth_and_errors(device):
    img, lights, sc, mat = make_case("sphere", 24, "perspective", "point", "blinn-phong", device=device)
    s = PixelSolver(img.shape[:3], sc.camera, lights, mat, SolverConfig(starts=2), device=device)
    a = s.run(img, sc.mask, depth=sc.depth)
    s.upload(img, sc.mask, depth=np.full_like(sc.depth, float(sc.depth[sc.mask].mean())))
    s.set_depth(sc.depth)
    s.step()
    b = s.fetch(("normals", "residual"))
    np.testing.assert_array_equal(a["normals"], b["normals"])
    with pytest.raises(ValueError, match="depth"):
        s.set_depth(np.zeros_like(sc.depth))
    with pytest.raises(ValueError, match="save"):
        PixelSolver(img.shape[:3], sc.camera, lights, mat, device=device).merge_saved()
    with pytest.raises(ValueError, match="normals"):
        s.set_start(np.zeros((3, 3, 3)))


def test_recorded_launches_kept_per_config_and_material(device):
    """set_config / set_material switch to the recorded launches of that (config, material) pair (kept for the
    last SOLVER_CMD_SETS pairs) instead of dropping them: switching back reuses the same recorded objects, and
    every solve equals a fresh solver's with that config and material."""
    from gpps.names import SOLVER_CMD_SETS

    img, lights, sc, mat = make_case("sphere", 32, "perspective", "directional", "cook-torrance", device=device)
    m = sc.mask
    a, b = SolverConfig(starts=3), SolverConfig(starts=1, max_iters=7)
    other = replace(mat, ks=0.5 * mat.ks)
    s = PixelSolver(img.shape[:3], sc.camera, lights, mat, a, device=device)
    assert s._cmds is s._cmd_sets[(a, mat)]  # noqa: SLF001  (the first pair's set, from the start)
    s.upload(img, m)

    def fresh(cfg, material):
        with PixelSolver(img.shape[:3], sc.camera, lights, material, cfg, device=device) as f:
            return f.run(img, m)

    want = {(cfg, mt): fresh(cfg, mt) for cfg in (a, b) for mt in (mat, other)}
    s.set_config(a)
    s.step()
    held = dict(s._cmds)  # noqa: SLF001
    assert held
    for cfg, mt in ((b, mat), (a, other), (b, other), (a, mat)):
        s.set_config(cfg)
        s.set_material(mt)
        s.step()
        got = s.fetch(NAMES)
        for k in NAMES:
            np.testing.assert_array_equal(got[k], want[(cfg, mt)][k], err_msg=f"{k} {cfg.starts} {mt.ks}")
    assert all(s._cmds[k] is v for k, v in held.items())  # noqa: SLF001  (a, mat) again: the same objects
    for i in range(SOLVER_CMD_SETS + 1):
        s.set_config(replace(b, max_iters=8 + i))
    assert len(s._cmd_sets) == SOLVER_CMD_SETS  # noqa: SLF001
    assert (a, mat) not in s._cmd_sets  # noqa: SLF001  (the oldest pairs dropped)
    s.close()


def test_checked_upload_defers_the_intensity_scale(device):
    """A checked upload (the caller ran check_observations) skips the grey values' percentile; a later config with
    the smoothness term computes it from the device's frame and the upload's mask: the same scale and the same
    smoothed solve as an unchecked upload; a dark frame's warning is the caller's then."""
    img, lights, sc, mat = make_case("sphere", 32, "perspective", "directional", "cook-torrance", device=device)
    noisy = np.clip(img + np.random.default_rng(3).normal(0.0, 0.01, img.shape).astype(np.float32), 0.0, None)
    half = sc.mask.copy()
    half[:, :16] = False  # (a mask the re-solve changes after the upload: the scale keeps the upload's)
    smooth = SolverConfig(starts=2, smoothness=0.3)
    outs, scales = [], []
    for checked in (False, True):
        s = PixelSolver(img.shape[:3], sc.camera, lights, mat, SolverConfig(starts=2), device=device)
        s.upload(noisy, sc.mask, checked=checked)
        assert (s.intensity_scale is None) == checked
        s.set_mask(half)
        s.set_config(smooth)
        scales.append(s.intensity_scale)
        s.step()
        outs.append(s.fetch(NAMES))
    grey = noisy[:, sc.mask].mean(axis=-1)
    assert scales[0] == scales[1] == float(np.percentile(grey, 99.0))
    for k in NAMES:
        np.testing.assert_array_equal(outs[1][k], outs[0][k], err_msg=k)
    s = PixelSolver(img.shape[:3], sc.camera, lights, mat, SolverConfig(starts=2), device=device)
    with pytest.warns(UserWarning, match="no observation inside the mask is lit"):
        s.upload(np.zeros_like(img), sc.mask)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s.upload(np.zeros_like(img), sc.mask, checked=True)

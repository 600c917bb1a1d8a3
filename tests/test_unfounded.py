"""Fits whose albedo the data do not fix (``FLAG_UNFOUNDED``, gpps.kernels.solve_common.unfounded_flag).

The case is real: a 13 x 13 crop of a Mitsuba development capture (rough-plastic spheres on a plane, 12 point
lights, interreflections; ``tests/data/unfounded_patch.npz``, written by perf/unfounded_patch.py) whose centre
pixel, at a sphere's rim, the plastic fit turns grazing to the view, where the model's diffuse term vanishes: albedo
8258 against its neighbours' 0.2-0.4 (the folder flow returned 4.5e5 there before session 35).

Reference: the rule in numpy from its definition, on the solver's own outputs (fitted albedo, final weights): a
pixel is unfounded when ``grey(kd) * UNFOUNDED_SHADING > max_k grey(I_k) / grey(E_k(p))`` over the observations
in the fit (weight not 0 and not ``ASIDE_WEIGHT``), with ``E_k(p) = intensity_k / |p - x_k|^2`` at the pixel's
point ``p`` on the given depth.  Pixels within 1e-3 (relative) of the threshold are left out of the comparison
(float32 against float64).  Every solve path that stores a free-albedo fit is run: one thread a pixel, the
lights-parallel lanes (one lane on the CPU, 32 with ``enable_cpu_blocks``) and the starts-parallel split.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import gpps
from gpps.lights import PointLights
from gpps.material import Material
from gpps.names import ASIDE_WEIGHT, FLAG_ALBEDO_FROM_NEIGHBOURS, FLAG_FEW_OBSERVATIONS, FLAG_UNFOUNDED
from gpps.names import UNFOUNDED_SHADING
from gpps.pipeline.solver import PixelSolver, SolverConfig

DATA = Path(__file__).parent / "data" / "unfounded_patch.npz"
CENTRE = (6, 6)


def _patch():
    d = np.load(DATA)
    cam = gpps.camera.camera_from_K(d["K"])
    lights = PointLights(d["positions"], d["intensities"])
    mat = Material.from_dict(json.loads(str(d["material"])))
    return d["images"], d["mask"].astype(bool), d["depth"], cam, lights, mat


def _config(**kw):
    # the solver settings gpps.reconstruct takes for more than 6 images (gpps.flows.reconstruction._prepare)
    return SolverConfig(robust="cauchy", shadow_threshold=0.02, shadow_relative=0.1, starts=4, **kw)


def _solve(cfg, device):
    img, mask, depth, cam, lights, mat = _patch()
    s = PixelSolver(img.shape[:3], cam, lights, mat, cfg, device=device)
    try:
        out = s.run(img, mask, depth=depth)
    finally:
        s.close()
    return out, img, mask, depth, cam, lights


def _reference(out, img, mask, depth, cam, lights):
    """(H, W) bool expected FLAG_UNFOUNDED, (H, W) bool pixels clear of the threshold."""
    p = cam.backproject(depth)  # (H, W, 3)
    d = np.asarray(lights.positions, float)[:, None, None, :] - p[None]
    e = np.asarray(lights.intensities, float).mean(-1)[:, None, None] / np.einsum("khwc,khwc->khw", d, d)
    w = out["weights"]
    fit = (w != 0.0) & (w != np.float32(ASIDE_WEIGHT))
    ratio = np.where(fit, img.astype(np.float64).mean(-1) / e, 0.0)
    floor = ratio.max(axis=0)
    level = out["albedo"].astype(np.float64).mean(-1) * UNFOUNDED_SHADING
    clear = np.abs(level - floor) > 1e-3 * np.maximum(level, floor)
    return (level > floor) & mask, clear & mask


@pytest.mark.parametrize("path", ["one-thread", "lanes", "lanes-cpu-blocks", "split"])
def test_unfounded_flag_follows_its_rule(path, device, monkeypatch):
    import warp as wp

    if path == "lanes-cpu-blocks":
        if device != "cpu":
            pytest.skip("enable_cpu_blocks concerns the CPU backend")
        monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    kw = {"one-thread": {}, "split": {"split_starts": True}}.get(path, {"parallel": "lights"})
    out, img, mask, depth, cam, lights = _solve(_config(neighbour_radius=0, **kw), device)
    expected, clear = _reference(out, img, mask, depth, cam, lights)
    got = (out["flags"] & FLAG_UNFOUNDED) != 0
    assert np.array_equal(got[clear], expected[clear])
    assert np.all(got[~mask] == 0)
    # the centre is the case: flagged, with the FEW bit that sends it to the neighbour pass
    assert expected[CENTRE] and clear[CENTRE]
    assert out["flags"][CENTRE] & FLAG_FEW_OBSERVATIONS
    assert out["albedo"][CENTRE].mean() > 100.0  # (the free albedo the flag reports)
    # the others are founded: the flag marks the exception, not the rim
    assert np.count_nonzero(got & mask) <= 2


def test_unfounded_pixel_takes_its_neighbours_albedo(device):
    out, img, mask, *_ = _solve(_config(), device)  # (the default neighbour pass)
    f = out["flags"][CENTRE]
    assert f & FLAG_UNFOUNDED and f & FLAG_FEW_OBSERVATIONS and f & FLAG_ALBEDO_FROM_NEIGHBOURS
    grey = out["albedo"].mean(-1)
    ok = mask & ((out["flags"] & FLAG_FEW_OBSERVATIONS) == 0)
    assert np.percentile(grey[ok], 1) <= grey[CENTRE] <= np.percentile(grey[ok], 99)
    assert grey[mask].max() < 2.0  # (no free albedo left anywhere in the patch)

"""DiLiGenT ball/bear: a fast subsampled check in the default run, full numbers in perf/diligent_calibrated.py."""

import numpy as np
import pytest

from gpps.camera import camera_from_K
from gpps.io import read_dataset
from gpps.lights import DirectionalLights
from gpps.material import Material
from gpps.host.metrics import normal_errors
from gpps.flows.photometric import solve_normals

OPTS = dict(shadow_threshold=0.02, robust="cauchy", robust_scale=0.1, irls_rounds=3, starts=4, max_iters=30)


def _load(data_root, name, every=1, images=None):
    ds = read_dataset(data_root / "diligent" / name, indices=images)
    raw = ds.images * np.asarray(ds.light_intensities, np.float32)[:, None, None, :]
    valid = ~np.any(raw >= 0.995, axis=-1)
    sub = np.zeros_like(ds.mask)
    sub[::every, ::every] = True
    return ds, ds.mask & sub, valid


def test_ball_subsampled_robust_beats_least_squares(data_root):
    ds, m, valid = _load(data_root, "ball", every=3, images=range(0, 96, 2))
    L = DirectionalLights(ds.light_directions)
    cam = camera_from_K(ds.K)
    ls = solve_normals(ds.images, m, L, camera=cam, solver="none")
    ours = solve_normals(ds.images, m, L, camera=cam, material=Material("blinn-phong", ks=0.1, shininess=80.0), valid=valid, **OPTS)
    e_ls = normal_errors(ls.normals, ds.normal_gt, m)["mean"]
    e = normal_errors(ours.normals, ds.normal_gt, m)["mean"]
    assert 3.0 < e_ls < 6.0
    assert e < e_ls - 1.0, (e, e_ls)


@pytest.mark.slow
@pytest.mark.parametrize("name,published", [("ball", 4.10), ("bear", 8.39)])
def test_full_96_robust_beats_least_squares(data_root, name, published):
    ds, m, valid = _load(data_root, name)
    L = DirectionalLights(ds.light_directions)
    cam = camera_from_K(ds.K)
    ls = solve_normals(ds.images, m, L, camera=cam, solver="none")
    e_ls = normal_errors(ls.normals, ds.normal_gt, m)["mean"]
    assert abs(e_ls - published) < 1.0  # our mask/normalisation: 4.29 and 8.94 measured
    ours = solve_normals(ds.images, m, L, camera=cam, material=Material("blinn-phong", ks=0.1, shininess=80.0), valid=valid, **OPTS)
    assert normal_errors(ours.normals, ds.normal_gt, m)["mean"] < e_ls

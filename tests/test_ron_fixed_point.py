"""RON's rounds stop at Algorithm 2's fixed point: a later material fit that keeps the round's material.

Ground truth: gpps's Cook-Torrance bumps (perspective, 3 directional lights, 16-bit, the material withheld), where
the third fit finds no candidate lower than the second's estimate.  The round the pipeline used to run after it
solved with the same material from its own normals: the test runs it (the stop switched off) and finds the same
normals and the same material.
"""

import numpy as np
import pytest

import gpps
from conftest import RENDER_DEVICE
from gpps.flows.ron import RON
from gpps.host.metrics import angular_error


def _capture(size=64):
    sc = gpps.make_scene("bumps", size, "perspective")
    L = gpps.default_lights("directional", 3, layout="ring")
    true = gpps.Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)
    img = gpps.render(sc, true, L, bits=16, device=RENDER_DEVICE) / L.intensities[:, None, None, :]
    return img, sc, gpps.DirectionalLights(L.directions)


def _reconstruct(img, sc, lights, device):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", gpps.GppsWarning)  # (the clipped highlights' note)
        return gpps.reconstruct(img, sc.mask, lights, camera=sc.camera, material="cook-torrance", device=device)


def test_a_kept_material_ends_the_rounds(device, monkeypatch):
    img, sc, lights = _capture()
    rec = _reconstruct(img, sc, lights, device)
    fits = rec.details.material_fit
    assert rec.converged and rec.rounds == len(fits) == 3
    assert fits[-1]["kept"] and not fits[-1]["grid"] and not fits[-2]["kept"]
    # the grid fit is never kept, and the first later fit moves the material (the grid fit's resolution is coarse)
    assert fits[0]["grid"] and not fits[0]["kept"] and fits[1]["values"] != fits[0]["values"]
    # the material kept bit for bit: the second fit's values, which the third round's normals were solved with
    assert fits[-1]["values"] == fits[-2]["values"] == rec.estimated
    assert gpps.normal_errors(rec.normals, sc.normals, sc.mask)["mean"] < 0.05

    # the round after it, as the loop ran before the stop: the same normals, the material kept again
    fit = RON._fit_material

    def unkept(self, *args, **kwargs):
        material, info = fit(self, *args, **kwargs)
        return material, dict(info, kept=False)

    monkeypatch.setattr(RON, "_fit_material", unkept)
    more = _reconstruct(img, sc, lights, device)
    assert more.rounds == 4 and more.converged
    assert more.estimated == rec.estimated
    assert more.details.normal_change_deg[-1] < 1e-3  # (the extra round moved the normals by this)
    err = angular_error(more.normals, rec.normals, sc.mask)[sc.mask]
    assert float(np.max(err)) < 1e-2
    e0 = gpps.normal_errors(rec.normals, sc.normals, sc.mask)["mean"]
    e1 = gpps.normal_errors(more.normals, sc.normals, sc.mask)["mean"]
    assert e0 == pytest.approx(e1, abs=1e-4)


"""The model comparison's evidence test (gpps.host.model_evidence, issue 25): the configured reflectance model is
kept unless another's sampled energy is lower beyond the sample's noise.  Checked against independent
computations (the pipeline's trimmed energy, scipy's paired t statistic) on residuals drawn here, and through
RON on gpps renders (the rendered model is chosen when it is another; with an impossible level, never)."""

import numpy as np
import pytest
from scipy import stats

import gpps
from gpps import names
from gpps.host.model_evidence import energy_drop_evidence
from gpps.pipeline.material import trimmed_energy

TRIM = 0.02


def _residuals(p=2000, seed=0):
    rng = np.random.default_rng(seed)
    return np.abs(rng.normal(0.0, 0.006, p)), rng


def test_energies_and_statistic_match_independent_formulas():
    """The energies are the pipeline's trimmed energy of each model; ``z`` is the paired t statistic of the
    squared residuals over the pixels both energies keep (scipy)."""
    a, rng = _residuals()
    b = a * (1.0 + rng.normal(-0.02, 0.1, a.size))
    ev = energy_drop_evidence(a, b, TRIM)
    assert ev["energy_base"] == pytest.approx(float(trimmed_energy(a, TRIM)), rel=1e-12)
    assert ev["energy_other"] == pytest.approx(float(trimmed_energy(b, TRIM)), rel=1e-12)
    assert ev["drop"] == pytest.approx(1.0 - ev["energy_other"] / ev["energy_base"], rel=1e-12)
    keep = int(round(a.size * (1 - TRIM)))
    both = np.zeros(a.size, bool)
    both[np.intersect1d(np.argsort(a ** 2)[:keep], np.argsort(b ** 2)[:keep])] = True
    assert ev["pixels"] == int(both.sum())
    t = stats.ttest_rel(a[both] ** 2, b[both] ** 2).statistic
    assert ev["z"] == pytest.approx(float(t), rel=1e-9)
    assert ev["z_critical"] == names.MODEL_SWITCH_Z


def test_a_clear_drop_is_significant_and_a_noise_sized_one_is_not():
    """A 10 % lower residual with 5 % per-pixel scatter is evidence; 0.1 % under 10 % scatter is within the
    sample's noise; a higher energy never is, however consistent."""
    a, rng = _residuals(seed=1)
    clear = energy_drop_evidence(a, a * (0.9 + rng.normal(0.0, 0.05, a.size)), TRIM)
    assert clear["significant"] and clear["z"] > 10 and clear["drop"] > 0.1
    small = energy_drop_evidence(a, a * (0.999 + rng.normal(0.0, 0.1, a.size)), TRIM)
    assert not small["significant"] and abs(small["drop"]) < 0.02
    worse = energy_drop_evidence(a, a * 1.05, TRIM)
    assert not worse["significant"] and worse["drop"] < 0


def test_level_is_a_one_sided_one_percent_test():
    """Under the null (the other model's squared residuals differ by symmetric noise only) the test rejects in
    about 1 % of samples (500 draws: at most 3 %)."""
    rejected = 0
    rng = np.random.default_rng(7)
    for _ in range(500):
        a = np.abs(rng.normal(0.0, 1.0, 600))
        b = np.sqrt(np.maximum(a * a + rng.normal(0.0, 0.2, a.size), 0.0))
        rejected += energy_drop_evidence(a, b, 0.0)["significant"]
    assert rejected <= 15


@pytest.mark.parametrize("a,b,match", [
    (np.ones(5), np.ones(4), "shape"),
    (np.ones((2, 3)), np.ones((2, 3)), "shape"),
    (np.array([1.0, np.nan]), np.ones(2), "finite"),
])
def test_bad_residuals_are_refused(a, b, match):
    with pytest.raises(ValueError, match=match):
        energy_drop_evidence(a, b, TRIM)


def test_empty_and_single_samples_decide_nothing():
    assert not energy_drop_evidence(np.zeros(0), np.zeros(0), TRIM)["significant"]
    assert not energy_drop_evidence(np.ones(1), 0.5 * np.ones(1), TRIM)["significant"]


def test_ron_switches_only_on_evidence(device, monkeypatch):
    """On a plastic render named Cook-Torrance first, RON's comparison records the test and takes plastic; with a
    level no sample can reach it keeps Cook-Torrance (the configured model is the null hypothesis)."""
    from test_ron_models import PLASTIC, _case

    img, L, sc, sat = _case(PLASTIC)
    kw = dict(camera=sc.camera, material=("cook-torrance", "plastic"), saturation=sat,
              reference_depth=float(sc.depth[sc.mask].mean()), device=device)
    rec = gpps.reconstruct(img, sc.mask, L, **kw)
    ev = rec.details.material_fit[0]["evidence"]
    assert set(ev) == {"plastic"} and ev["plastic"]["significant"] and ev["plastic"]["z"] > names.MODEL_SWITCH_Z
    assert ev["plastic"]["energy_other"] < 0.5 * ev["plastic"]["energy_base"]
    assert rec.material.brdf == "plastic"
    monkeypatch.setattr(names, "MODEL_SWITCH_Z", np.inf)
    kept = gpps.reconstruct(img, sc.mask, L, **kw)
    assert kept.material.brdf == "cook-torrance"
    assert not kept.details.material_fit[0]["evidence"]["plastic"]["significant"]


def test_pixels_without_a_residual_take_no_part(device, monkeypatch):
    """A sample pixel whose re-solve left no finite residual (under either model) is left out of the test, which
    still decides on the others; the reconstruction does not fail."""
    from test_ron_models import PLASTIC, _case

    from gpps.flows.ron import RON

    real = RON._sample_residuals
    sizes = []

    def holes(self, *args, **kwargs):
        r = real(self, *args, **kwargs).copy()
        r[::7] = np.nan
        sizes.append(r.size)
        return r

    monkeypatch.setattr(RON, "_sample_residuals", holes)
    img, L, sc, sat = _case(PLASTIC)
    rec = gpps.reconstruct(img, sc.mask, L, camera=sc.camera, material=("cook-torrance", "plastic"), saturation=sat,
                           reference_depth=float(sc.depth[sc.mask].mean()), device=device)
    ev = rec.details.material_fit[0]["evidence"]["plastic"]
    assert ev["significant"] and rec.material.brdf == "plastic"
    p = sizes[0]
    assert len(sizes) == 2 and 0 < ev["pixels"] <= p - len(range(0, p, 7))

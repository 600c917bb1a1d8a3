"""The interreflection compensation on the device-resident frame (issue 20's one data path), on every device.

* :meth:`Interreflections.indirect_total` and :meth:`Interreflections.subtract_from`
  (:mod:`gpps.kernels.interreflection_subtract`) against numpy from the stage's fetched gather: the albedo clipped to
  ``[0, max_albedo]`` (negative and NaN: 0), the frame less ``coef * kd * S`` clipped at 0, the other pixels untouched.
* :class:`gpps.flows.reconstruction.ResidentFrame` in :func:`reconstruct_subtracting`: the later rounds solve the
  frame the first reconstruction uploaded, changed on the device, and give what the host path (the corrected stack
  fetched, checked and uploaded again) gives.
"""

import numpy as np
import pytest

from test_interreflection import _self_lit

from gpps.camera import Orthographic
from gpps.pipeline.interreflection import InterreflectionConfig, Interreflections


def _stage(device, m, depth, n, images):
    st = Interreflections(images.shape[:3], Orthographic(1.0), InterreflectionConfig(max_sources=300), device=device)
    st.upload(depth, m, n, images)
    st.step()
    return st


def _albedo(m, kd=0.8):
    """An albedo map with the cases the clip must handle: negative, NaN and far too bright pixels."""
    rng = np.random.default_rng(3)
    alb = np.where(m[..., None], kd * (0.75 + 0.5 * rng.random(m.shape + (3,))), 0.0).astype(np.float32)
    ii, jj = m.nonzero()
    alb[ii[:4], jj[:4]] = -0.3
    alb[ii[4:8], jj[4:8], 1] = np.nan
    alb[ii[8:12], jj[8:12]] = 5.0e4
    return alb


@pytest.mark.parametrize("max_albedo", [1.25, np.inf])
def test_indirect_total_and_subtract_match_numpy(device, max_albedo):
    import warp as wp

    m, depth, n, lights, cam, direct, images = _self_lit(device)
    alb = _albedo(m)
    with _stage(device, m, depth, n, images) as st:
        S = st.fetch().astype(np.float64)  # (N, H, W, 3), 0 off the mask
        kd = np.clip(np.nan_to_num(alb.astype(np.float64)), 0.0, max_albedo)
        want_total = float((kd[None] * S).sum())
        got_total = st.indirect_total(alb, max_albedo=max_albedo)
        np.testing.assert_allclose(got_total, want_total, rtol=2e-5)  # (float32 sums of 24 terms per receiver)

        coef = 0.7
        want = np.maximum(images.astype(np.float64) - coef * kd[None] * S, 0.0)
        assert (want == 0).any() if np.isinf(max_albedo) else True  # (the clip at 0 is exercised with bright pixels)
        frame = wp.array(images, dtype=wp.vec3, device=device)
        st.subtract_from(frame, coef)
        got = frame.numpy()
        tol = 4 * np.finfo(np.float32).eps * float(images.max())
        np.testing.assert_allclose(got, want, rtol=0, atol=tol)
        np.testing.assert_array_equal(got[:, ~m], images[:, ~m])  # (off the mask untouched)

        # from observed images kept aside: the same frame, whatever the frame held; observed untouched
        observed = wp.array(images, dtype=wp.vec3, device=device)
        other = wp.zeros(images.shape[:3], dtype=wp.vec3, device=device)
        st.subtract_from(other, coef, observed=observed)
        np.testing.assert_allclose(other.numpy()[:, m], want[:, m], rtol=0, atol=tol)
        np.testing.assert_array_equal(observed.numpy(), images)


def test_subtract_checks(device):
    import warp as wp

    m, depth, n, lights, cam, direct, images = _self_lit(device)
    with _stage(device, m, depth, n, images) as st:
        frame = wp.array(images, dtype=wp.vec3, device=device)
        with pytest.raises(ValueError, match="indirect_total"):
            st.subtract_from(frame, 1.0)
        with pytest.raises(ValueError, match="albedo"):
            st.indirect_total(np.ones((3, 3, 3)))
        with pytest.raises(ValueError, match="max_albedo"):
            st.indirect_total(_albedo(m), max_albedo=0.0)
        st.indirect_total(_albedo(m), max_albedo=1.0)
        with pytest.raises(ValueError, match=r"frame: expected an \(8, 40, 40\) wp.vec3 array, got shape \(8, 40, 39\)"):
            st.subtract_from(wp.zeros((8, 40, 39), dtype=wp.vec3, device=device), 1.0)
        with pytest.raises(ValueError, match="frame: expected .* got ndarray"):
            st.subtract_from(images, 1.0)
        with pytest.raises(ValueError, match="observed: expected"):
            st.subtract_from(frame, 1.0, observed=wp.zeros((8, 40, 40), dtype=wp.float32, device=device))
        with pytest.raises(ValueError, match="coef"):
            st.subtract_from(frame, -1.0)


class _ResidentSolve:
    """``solve`` with a :class:`ResidentFrame` (as the folder flow's): Lambertian RON on the cap, true scale."""

    def __init__(self, m, lights, cam, device, config):
        self.m, self.lights, self.cam, self.device, self.config = m, lights, cam, device, config
        self.frame = None

    def __call__(self, images):
        from gpps.flows.reconstruction import ResidentFrame

        assert self.frame is None, "the later rounds run on the frame"
        self.frame = ResidentFrame(images, self.m, self.lights, camera=self.cam, material="lambertian",
                                   reference_depth=100.0, config=self.config, device=self.device)
        return self.frame.run()


def test_resident_rounds_match_the_host_rounds(device):
    """Two compensation rounds on the self-lit cap: the resident path (the frame changed on the device, solved again
    without an upload) against the host path (each round's corrected stack through ``reconstruct``): the same shares,
    the same normals (to 0.01 deg; the resident frame keeps the first upload's noise levels where the host path
    estimates them again on the corrected stack), both much better than no compensation."""
    import gpps
    from gpps.flows.interreflection import reconstruct_subtracting
    from gpps.flows.ron import RONConfig
    from gpps.pipeline.solver import PixelSolver

    m, depth, n, lights, cam, direct, images = _self_lit(device)
    config = RONConfig()

    def host(imgs, state={}):
        kw = dict(camera=cam, reference_depth=100.0, config=config, device=device)
        if "last" not in state:
            state["last"] = gpps.reconstruct(imgs, m, lights, material="lambertian", **kw)
        else:
            last = state["last"]
            state["last"] = gpps.reconstruct(imgs, m, lights, material=last.material, estimate=(), start=last, **kw)
        return state["last"]

    def maen(nn):
        return np.degrees(np.arccos(np.clip((nn[m] * n[m]).sum(-1), -1, 1))).mean()

    resident = _ResidentSolve(m, lights, cam, device, config)
    uploads = []
    real = PixelSolver.upload

    def counted(self, *a, **kw):
        uploads.append(1)
        return real(self, *a, **kw)

    PixelSolver.upload = counted
    try:
        rec_r, info_r = reconstruct_subtracting(resident, images, m, lights, cam, rounds=2, albedo_scale=1.0,
                                                device=device)
        n_resident = len(uploads)
        rec_h, info_h = reconstruct_subtracting(host, images, m, lights, cam, rounds=2, albedo_scale=1.0, device=device)
    finally:
        PixelSolver.upload = real
        resident.frame.close()
    assert info_r["resident"] and not info_h["resident"]
    assert resident.frame.runs == 3 and n_resident == 1  # (one upload: the first reconstruction's)
    np.testing.assert_allclose(info_r["indirect_share"], info_h["indirect_share"], rtol=1e-4)
    assert info_r["tau"] == info_h["tau"] == [1.0, 1.0]
    diff = np.degrees(np.arccos(np.clip((rec_r.normals[m] * rec_h.normals[m]).sum(-1), -1, 1)))
    print(f"resident - host: mean {diff.mean():.2e} deg, max {diff.max():.2e} deg")
    assert diff.mean() < 0.01 and diff.max() < 0.2, (diff.mean(), diff.max())
    first = gpps.reconstruct(images, m, lights, camera=cam, material="lambertian", reference_depth=100.0, config=config,
                             device=device)
    assert maen(rec_r.normals) < 0.5 * maen(first.normals), (maen(first.normals), maen(rec_r.normals))
    np.testing.assert_allclose(rec_r.albedo[m].mean(), rec_h.albedo[m].mean(), rtol=1e-4)


def test_resident_frame_checks(device):
    from gpps.flows.reconstruction import ResidentFrame

    m, depth, n, lights, cam, direct, images = _self_lit(device)
    frame = ResidentFrame(images, m, lights, camera=cam, material="lambertian", reference_depth=100.0, device=device)
    assert frame.images is None and frame.scale == 1.0
    with pytest.raises(RuntimeError, match="run first"):
        frame._ron.rerun((n, None), frame._ron.material)
    rec = frame.run()
    assert frame.images is not None and tuple(frame.images.shape) == images.shape[:3]
    with pytest.raises(TypeError, match="start: expected a Reconstruction"):
        frame.again((rec.normals, rec.highlight))
    frame.close()
    with pytest.raises(RuntimeError, match="closed"):
        frame.again(rec)
    with pytest.raises(ValueError, match=r"mask: expected shape \(10, 40\)"):  # (checked at construction)
        ResidentFrame(images[:, :10], m, lights, camera=cam, device=device)

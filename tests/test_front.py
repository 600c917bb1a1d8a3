"""DGMC's device-resident front (gpps.pipeline.front, gpps.kernels.front, gpps.host.dgmc.front_rings) against the
former host loop over rings (tests/front_reference.py): identical rings, sources, starts, merges and results on
rendered scenes and on every device, and no host<->device copy per ring."""

import numpy as np
import pytest
from cases import copy_counter
from front_reference import propagate_front_host

from gpps._runtime import warp
from gpps.host.dgmc import DGMCConfig, dgmc_start, front_rings
from gpps.host.merge import ranks_better
from gpps.names import FLAG_FEW_OBSERVATIONS
from gpps.pipeline.front import DeviceFront, propagate_front, propagate_front_device
from gpps.pipeline.solver import PixelSolver, SolverConfig

_FIELDS = ("normals", "albedo", "residual", "flags", "iterations", "ring", "source", "won")


def _case(device, scene, size, camera, brdf, light_kind, n_lights, parallel="auto"):
    """A rendered frame on a PixelSolver, its multi-start solution (the front's sources), DGMC's highlights and
    curvatures (host), and the depth the solver needs (point lights)."""
    from gpps.flows.synthetic import default_lights, render
    from gpps.host.scenes import make_scene
    from gpps.lights import DirectionalLights, PointLights
    from gpps.material import Material

    sc = make_scene(scene, size, camera)
    mat = Material.default_for(brdf)
    L = default_lights(light_kind, n_lights, layout="ring" if n_lights <= 4 else "spiral")
    img = render(sc, mat, L, bits=16, device=device)
    img = (img / np.asarray(L.intensities, np.float32)[:, None, None, :]).astype(np.float32)
    lu = DirectionalLights(L.directions) if light_kind == "directional" else PointLights(L.positions)
    depth = sc.depth if light_kind == "point" else None
    solver = PixelSolver(img.shape[:3], sc.camera, lu, mat, SolverConfig(solver="none"), device=device)
    ls = solver.run(img, sc.mask, depth=depth)
    nrm = ls["normals"].astype(np.float64)
    ok = sc.mask & (np.abs(np.linalg.norm(nrm, axis=-1) - 1.0) < 1e-3)
    nrm[~ok] = (0.0, 0.0, 1.0)
    pts = sc.camera.backproject(np.where(sc.mask, sc.depth, 1.0)) if light_kind == "point" else None
    # (point-lit images divided by unit intensities are ~100x darker: a margin to match)
    cfg = DGMCConfig(margin=2e-4) if pts is not None else None
    dg = dgmc_start(img, sc.mask, nrm, lights=lu, points=pts, config=cfg)
    solver.set_config(SolverConfig(parallel=parallel))
    solver.set_mask(sc.mask)
    solver.step()
    sol = solver.fetch(("normals", "albedo", "residual", "iterations", "flags"))
    return img, sc, solver, dg, sol, depth


def _assert_same(a, b):
    for k in _FIELDS:
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    assert a.n_rings == b.n_rings


# Measured when written (CPU, 48-64 px): every field bit-identical to the host loop in every case.
@pytest.mark.parametrize(
    "scene, size, camera, brdf, light_kind, n_lights, curvatures, keep_better",
    [
        ("sphere", 64, "orthographic", "blinn-phong", "directional", 3, True, True),
        ("bumps", 64, "perspective", "cook-torrance", "directional", 3, True, True),
        ("bumps", 48, "perspective", "cook-torrance", "directional", 12, False, False),
        ("sphere", 48, "perspective", "blinn-phong", "point", 3, True, False),
    ],
)
def test_device_front_equals_the_host_loop(device, scene, size, camera, brdf, light_kind, n_lights, curvatures,
                                           keep_better):
    img, sc, solver, dg, sol, depth = _case(device, scene, size, camera, brdf, light_kind, n_lights)
    hm = dg.highlight
    assert hm.sum() > 50
    kw = dict(gaussian=dg.gaussian, mean=dg.mean) if curvatures else {}
    ref = propagate_front_host(solver, img, sc.mask, hm, sol, depth=depth, keep_better=keep_better, **kw)
    cfg = solver.config
    dev = propagate_front(solver, img, sc.mask, hm, sol, depth=depth, keep_better=keep_better, **kw)
    assert ref.n_rings > 3
    _assert_same(dev, ref)
    assert solver.config == cfg  # restored
    if keep_better:
        assert (dev.residual[sc.mask] <= sol["residual"][sc.mask]).all() and dev.won.any()
    else:
        np.testing.assert_array_equal(dev.won, dev.ring > 0)
    # the frame already on the solver (images=None, as RON calls it): the same front
    again = propagate_front(solver, None, sc.mask, hm, sol, keep_better=keep_better, **kw)
    _assert_same(again, ref)


@pytest.mark.parametrize("keep_better", [True, False])
def test_front_from_and_into_the_solver(device, keep_better):
    """propagate_front_device (RON's device rounds): the solution read from the solver's outputs and the merge
    written back there is the host path's (the fetched FrontResult merged into the solve), bit for bit: normals,
    albedo, residual and flags replaced, the front's evaluations added; and the start normals it returns are the
    sources' merged normals of FrontResult.source."""
    img, sc, solver, dg, sol, depth = _case(device, "bumps", 64, "perspective", "cook-torrance", "directional", 3)
    hm = dg.highlight
    kw = dict(gaussian=dg.gaussian, mean=dg.mean, keep_better=keep_better)
    ref = propagate_front(solver, None, sc.mask, hm, sol, **kw)
    # the solver's outputs hold the solve `sol` again (the front left its rings' solves there)
    solver.set_mask(sc.mask)
    solver.step()
    again = solver.fetch(("normals", "albedo", "residual", "iterations", "flags"))
    for k in again:
        np.testing.assert_array_equal(again[k], sol[k], err_msg=k)
    pix, nrm = propagate_front_device(solver, sc.mask, hm, **kw)
    got = solver.fetch(("normals", "albedo", "residual", "iterations", "flags"))
    for k in ("normals", "albedo", "residual", "flags"):
        np.testing.assert_array_equal(got[k], getattr(ref, k), err_msg=k)
    np.testing.assert_array_equal(got["iterations"], sol["iterations"] + ref.iterations)
    has = ref.source[..., 0] >= 0
    assert has.sum() > 50
    np.testing.assert_array_equal(np.sort(pix), np.flatnonzero(has.ravel()))
    want = ref.normals[ref.source[..., 0], ref.source[..., 1]].reshape(-1, 3)
    order = np.argsort(pix)
    np.testing.assert_array_equal(nrm[order], want[np.sort(pix)])


def test_kept_front_stage_equals_a_fresh_one(device):
    """RON keeps one DeviceFront on its solver between runs (``front=``): each use of the kept stage gives what a
    stage built for the call gives, bit for bit; a stage on another solver is refused."""
    img, sc, solver, dg, sol, depth = _case(device, "bumps", 48, "perspective", "cook-torrance", "directional", 3)
    kw = dict(gaussian=dg.gaussian, mean=dg.mean, keep_better=True)
    names = ("normals", "albedo", "residual", "iterations", "flags")

    def from_solve(front):
        solver.set_mask(sc.mask)
        solver.step()  # (the solve the rings start from, again)
        pix, nrm = propagate_front_device(solver, sc.mask, dg.highlight, front=front, **kw)
        return pix, nrm, solver.fetch(names)

    want = from_solve(None)
    with DeviceFront(solver) as kept:
        for _ in range(2):
            got = from_solve(kept)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
            for k in names:
                np.testing.assert_array_equal(got[2][k], want[2][k], err_msg=k)
        other = PixelSolver(img.shape[:3], sc.camera, solver.lights, solver.material, SolverConfig(solver="none"),
                            device=device)
        try:
            with pytest.raises(ValueError, match="front"):
                propagate_front_device(other, sc.mask, dg.highlight, front=kept, **kw)
        finally:
            other.close()


@pytest.mark.parametrize("parallel", ["pixels", "lights"])
def test_device_front_equals_the_host_loop_either_kernel(device, parallel):
    """The ring solves through either solve kernel (one thread a pixel, or the lights split over lanes, which also
    leaves the pixels outside the ring alone): the host loop's result."""
    img, sc, solver, dg, sol, depth = _case(device, "sphere", 48, "orthographic", "blinn-phong", "directional", 12,
                                            parallel=parallel)
    hm = dg.highlight
    kw = dict(gaussian=dg.gaussian, mean=dg.mean)
    ref = propagate_front_host(solver, None, sc.mask, hm, sol, **kw)
    assert ref.n_rings > 3
    _assert_same(propagate_front(solver, None, sc.mask, hm, sol, **kw), ref)


def test_rings_and_sources_equal_the_host_loop(device):
    """front_rings (all rings at once, before any solve) gives the host loop's rings, and the device's source
    choice its sources, with and without the curvature test, with a widened tolerance and with no widening."""
    img, sc, solver, dg, sol, depth = _case(device, "bumps", 48, "perspective", "cook-torrance", "directional", 3)
    hm = dg.highlight
    ring, pixels, sizes = front_rings(sc.mask, hm)
    curv = dict(gaussian=dg.gaussian, mean=dg.mean)
    for kw in ({}, curv, dict(curv, config=DGMCConfig(tolerance=0.2, widen_steps=0)),
               dict(curv, config=DGMCConfig(tolerance=0.01, widen_factor=1.5, widen_steps=5))):
        ref = propagate_front_host(solver, None, sc.mask, hm, sol, keep_better=False, **kw)
        np.testing.assert_array_equal(ring, ref.ring)
        assert sizes.size - 1 == ref.n_rings and sizes[0] == 0
        np.testing.assert_array_equal(np.repeat(np.arange(ref.n_rings + 1), sizes), ring.ravel()[pixels])
        assert np.unique(pixels).size == pixels.size == (ring > 0).sum()
        dev = propagate_front(solver, None, sc.mask, hm, sol, keep_better=False, **kw)
        np.testing.assert_array_equal(dev.source, ref.source)


def test_no_copies_per_ring(device):
    """Between two rings' progress reports nothing goes between host and device (warp.copy, which
    array.assign uses, array.numpy and warp.array(data=...) are counted)."""
    img, sc, solver, dg, sol, depth = _case(device, "sphere", 48, "orthographic", "blinn-phong", "directional", 3)
    marks = []
    with copy_counter() as n:
        fr = propagate_front(solver, None, sc.mask, dg.highlight, sol, gaussian=dg.gaussian, mean=dg.mean,
                             progress=lambda k, _t, _m: marks.append(n[0]))
        end = n[0]
        ref_marks = []
        n[0] = 0
        propagate_front_host(solver, None, sc.mask, dg.highlight, sol, gaussian=dg.gaussian, mean=dg.mean,
                             progress=lambda k, _t, _m: ref_marks.append(n[0]))
    assert fr.n_rings > 3 and len(marks) == fr.n_rings
    assert np.all(np.diff(marks) == 0), marks
    assert end - marks[-1] <= 7  # one fetch at the end: six outputs and the sources
    assert np.all(np.diff(ref_marks) > 0)  # (the counter sees the host loop's per-ring copies)


def _dev(v, device):
    wp = warp()
    return wp.array(v, dtype=wp.vec3, device=device) if v.ndim == 3 else wp.array(v, device=device)


def test_merge_and_start_kernels_against_numpy(device):
    """front_merge_kernel on one ring's slice of the pixel list: the lower residual without the few-observations
    flag wins (ties keep the current solution: gpps.host.merge.ranks_better), the ring solve's own evaluations,
    won set where taken, pixels off the slice untouched; front_start_kernel copies each source's normal."""
    from gpps.kernels import front as fk

    wp = warp()
    rng = np.random.default_rng(0)
    h, w = 9, 11
    new = {"normals": rng.normal(size=(h, w, 3)).astype(np.float32), "albedo": rng.random((h, w, 3)).astype(np.float32),
           "residual": rng.random((h, w)).astype(np.float32), "iterations": rng.integers(1, 9, (h, w)).astype(np.int32),
           "flags": rng.choice([0, FLAG_FEW_OBSERVATIONS, 1, 1 | FLAG_FEW_OBSERVATIONS], (h, w)).astype(np.int32)}
    cur = {"normals": rng.normal(size=(h, w, 3)).astype(np.float32), "albedo": rng.random((h, w, 3)).astype(np.float32),
           "residual": rng.random((h, w)).astype(np.float32), "flags": rng.integers(0, 4, (h, w)).astype(np.int32)}
    cur["residual"][::3] = new["residual"][::3]  # ties
    flat = rng.permutation(h * w).astype(np.int32)
    sources = rng.integers(0, h * w, h * w).astype(np.int32)
    pix, srcs = wp.array(flat, device=device), wp.array(sources, device=device)
    a, c = 17, 40
    on = np.zeros(h * w, bool)
    on[flat[a:a + c]] = True
    on = on.reshape(h, w)
    for keep in (1, 0):
        d = {key: _dev(v, device) for key, v in new.items()}
        cu = {key: _dev(v, device) for key, v in cur.items()}
        it = wp.full((h, w), -7, dtype=wp.int32, device=device)
        won = wp.zeros((h, w), dtype=wp.uint8, device=device)
        wp.launch(fk.front_merge_kernel, dim=c,
                  inputs=[pix, a, w, keep, int(FLAG_FEW_OBSERVATIONS), d["normals"], d["albedo"], d["residual"],
                          d["iterations"], d["flags"]],
                  outputs=[cu["normals"], cu["albedo"], cu["residual"], cu["flags"], it, won], device=device)
        take = on & (ranks_better(new["residual"], new["flags"], cur["residual"]) if keep else True)
        assert 0 < take.sum() < c or not keep
        for key in cur:
            want = np.where(take[..., None] if cur[key].ndim == 3 else take, new[key], cur[key])
            np.testing.assert_array_equal(cu[key].numpy(), want, err_msg=key)
        np.testing.assert_array_equal(it.numpy(), np.where(on, new["iterations"], -7))
        np.testing.assert_array_equal(won.numpy().astype(bool), take)
    start = _dev(np.zeros((h, w, 3), np.float32), device)
    wp.launch(fk.front_start_kernel, dim=c, inputs=[pix, srcs, a, w, _dev(cur["normals"], device)], outputs=[start],
              device=device)
    want = np.zeros((h, w, 3), np.float32)
    want.reshape(-1, 3)[flat[a:a + c]] = cur["normals"].reshape(-1, 3)[sources[a:a + c]]
    np.testing.assert_array_equal(start.numpy(), want)


@pytest.mark.parametrize("parallel", ["pixels", "lights"])
def test_select_pixels_and_subset_step(device, parallel):
    """select_pixels sets exactly the slice on the device; a subset step (with either solve kernel) solves those
    pixels as a step of the same mask set from the host does, and leaves every other pixel's outputs as they were."""
    img, sc, solver, dg, sol, depth = _case(device, "sphere", 32, "orthographic", "blinn-phong", "directional", 3,
                                            parallel=parallel)
    wp = warp()
    names = ("normals", "albedo", "residual", "iterations", "flags", "cond")
    flat = np.flatnonzero(sc.mask.ravel()).astype(np.int32)[::-1].copy()
    pix = wp.array(flat, dtype=wp.int32, device=device)
    a, c = 5, 60
    sel = np.zeros(sc.mask.size, bool)
    sel[flat[a:a + c]] = True
    sel = sel.reshape(sc.mask.shape)
    solver.select_pixels(pix, a, c, sel.sum(1))
    np.testing.assert_array_equal(solver.mask.numpy().astype(bool), sel)
    before = solver.fetch(names)
    solver.step(subset=True)
    got = solver.fetch(names)
    solver.set_mask(sel)
    solver.step()
    want = solver.fetch(names)
    for k in names:
        if device.startswith("cuda") and k != "flags":
            # CUDA: the subset step and the whole-mask step are separately compiled launches (the starts-parallel
            # cold solve on CUDA); their float32 results differ by contraction (FMA), measured <= 1.3e-6, and so
            # do the iterations' paths (evaluation counts up to 6 apart of ~130)
            if k != "iterations":
                np.testing.assert_allclose(got[k][sel], want[k][sel], rtol=1e-5, atol=1e-5, err_msg=k)
        else:
            np.testing.assert_array_equal(got[k][sel], want[k][sel], err_msg=k)
        np.testing.assert_array_equal(got[k][~sel], before[k][~sel], err_msg=k)
    solver.select_pixels(pix, 0, 0)
    assert not solver.mask.numpy().any()
    with pytest.raises(ValueError, match="pixels"):
        solver.select_pixels(flat, 0, 3)
    with pytest.raises(ValueError, match="pixels"):
        solver.select_pixels(wp.array(flat.astype(np.float32), device=device), 0, 3)
    with pytest.raises(ValueError, match="start, count"):
        solver.select_pixels(pix, flat.size - 2, 3)
    with pytest.raises(ValueError, match="rows"):
        solver.select_pixels(pix, 0, 3, np.ones(3))


def test_curvatures_read_on_the_device(device):
    """Curvature maps given as Warp float64 arrays (DeviceDGMC.gc / mc, as RON passes them) are rounded to float32
    on the device: the front equals the one given the host's float32 maps (DGMCStart's), bit for bit."""
    import warp as wp

    img, sc, solver, dg, sol, depth = _case(device, "bumps", 48, "perspective", "cook-torrance", "directional", 3)
    g64 = np.asarray(dg.gaussian, np.float64) * (1.0 + 1e-9)  # (float64 values that float32 rounds)
    m64 = np.asarray(dg.mean, np.float64) * (1.0 - 1e-9)
    assert not np.array_equal(g64, g64.astype(np.float32).astype(np.float64))
    ref = propagate_front(solver, None, sc.mask, dg.highlight, sol, gaussian=g64.astype(np.float32),
                          mean=m64.astype(np.float32))
    with DeviceFront(solver) as front:
        front.upload(sc.mask, dg.highlight, sol, gaussian=wp.array(g64, dtype=wp.float64, device=device),
                     mean=wp.array(m64, dtype=wp.float64, device=device))
        np.testing.assert_array_equal(front.gc.numpy(), g64.astype(np.float32).astype(np.float64))
        np.testing.assert_array_equal(front.mc.numpy(), m64.astype(np.float32).astype(np.float64))
        front.step()
        _assert_same(front.fetch(), ref)
        with pytest.raises(ValueError, match=r"^gaussian: expected a \(48, 48\) float64 array"):
            front.upload(sc.mask, dg.highlight, sol, gaussian=wp.array(g64.astype(np.float32), device=device),
                         mean=m64)


def test_stage_protocol_and_bad_input(device):
    img, sc, solver, dg, sol, depth = _case(device, "sphere", 32, "orthographic", "blinn-phong", "directional", 3)
    hm = dg.highlight
    with DeviceFront(solver) as front:
        with pytest.raises(RuntimeError, match="upload"):
            front.step()
        with pytest.raises(ValueError, match="solution"):
            front.upload(sc.mask, hm, {"normals": sol["normals"]})
        with pytest.raises(ValueError, match=r"solution\['flags'\]"):
            front.upload(sc.mask, hm, {**sol, "flags": sol["flags"][:-1]})
        with pytest.raises(ValueError, match="highlight"):
            front.upload(sc.mask, hm[:-1], sol)
        with pytest.raises(ValueError, match="mask"):
            front.upload(sc.mask[:-1], hm, sol)
        front.upload(sc.mask, hm, sol)
        front.step(keep_better=False)
        a = front.fetch()
        # the stage is reusable: a second upload and step give the same result
        front.upload(sc.mask, hm, sol)
        front.step(keep_better=False)
        _assert_same(front.fetch(), a)
    with pytest.raises(RuntimeError, match="closed"):
        front.fetch()

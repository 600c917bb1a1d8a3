"""DGMC on the device (gpps.pipeline.dgmc, gpps.kernels.dgmc) against the host reference (gpps.host.dgmc):
the O(N) highlight test, the labels and boundaries, the geodesic K-nearest lists (exact, also against a textbook
Dijkstra), the curvatures (4.16) and the start search (4.17-4.18), on rendered scenes and on every device."""

import heapq
import math

import numpy as np
import pytest

from gpps.host import dgmc as H
from gpps.lights import DirectionalLights, PointLights, ring_directions
from gpps.pipeline.dgmc import DeviceDGMC, dgmc_start_device


def _scene(scene, size, camera, light_kind, n_lights, bits=16, noise=0.0, brdf="blinn-phong"):
    """Rendered images divided by the intensities, unit-intensity lights, the scene, LS normals, points."""
    from gpps.flows.photometric import solve_normals
    from gpps.flows.synthetic import default_lights, render
    from gpps.host.scenes import make_scene
    from gpps.material import Material

    sc = make_scene(scene, size, camera)
    mat = Material.default_for(brdf)
    L = default_lights(light_kind, n_lights)
    img = render(sc, mat, L, bits=bits, noise=noise, device=None)  # the scene is data: render it wherever Warp runs
    img = (img / np.asarray(L.intensities, np.float32)[:, None, None, :]).astype(np.float32)
    Lu = DirectionalLights(L.directions) if light_kind == "directional" else PointLights(L.positions)
    depth = sc.depth if light_kind == "point" else None
    ls = solve_normals(img, sc.mask, Lu, camera=sc.camera, material=mat, solver="none", depth=depth, device=None)
    nrm = ls.normals.astype(np.float64)
    ok = sc.mask & (np.abs(np.linalg.norm(nrm, axis=-1) - 1.0) < 1e-3)
    nrm[~ok] = (0.0, 0.0, 1.0)
    pts = sc.camera.backproject(np.where(sc.mask, sc.depth, 1.0)) if light_kind == "point" else None
    return img, Lu, sc, nrm, pts


def _compare(h, d, truth=None, mask=None):
    """Agreement numbers of a device result d with the host's h (and both starts' MAEN against truth)."""
    out = {
        "maps_agree": float((h.highlights.maps == d.highlights.maps).mean()),
        "region_iou": float((h.highlight & d.highlight).sum() / max((h.highlight | d.highlight).sum(), 1)),
        "source_agree": float((h.source == d.source).all(-1)[h.highlight | d.highlight].mean())
        if (h.highlight | d.highlight).any() else 1.0,
    }
    if truth is not None:
        from gpps.host.metrics import angular_error

        hm = h.highlight | d.highlight
        out["maen_host"] = float(angular_error(h.normals, truth, mask)[hm].mean()) if hm.any() else 0.0
        out["maen_device"] = float(angular_error(d.normals, truth, mask)[hm].mean()) if hm.any() else 0.0
    return out


def _assert_same(h, d):
    hh, dh = h.highlights, d.highlights
    np.testing.assert_array_equal(dh.maps, hh.maps)
    np.testing.assert_array_equal(dh.saturated, hh.saturated)
    np.testing.assert_array_equal(d.highlight, h.highlight)
    np.testing.assert_array_equal(dh.labels, hh.labels)
    assert dh.n_regions == hh.n_regions
    np.testing.assert_array_equal(dh.boundary, hh.boundary)
    np.testing.assert_allclose(dh.predicted, hh.predicted, rtol=1e-6, atol=1e-7, equal_nan=True)
    scale_g = max(float(np.abs(h.gaussian).max()), 1e-30)
    scale_m = max(float(np.abs(h.mean).max()), 1e-30)
    np.testing.assert_allclose(d.gaussian, h.gaussian, rtol=0, atol=1e-6 * scale_g)
    np.testing.assert_allclose(d.mean, h.mean, rtol=0, atol=1e-6 * scale_m)
    np.testing.assert_array_equal(d.source, h.source)
    np.testing.assert_array_equal(d.rank, h.rank)
    np.testing.assert_allclose(d.distance, h.distance, rtol=1e-6, equal_nan=True)
    np.testing.assert_array_equal(d.tolerance, h.tolerance)
    np.testing.assert_array_equal(d.normals, h.normals)


# --------------------------------------------------------------------------- rendered scenes, host == device

# Measured when written (CPU, 64^2, default DGMCConfig): maps, regions, labels, boundaries, sources, ranks and
# start normals identical to the host on every case; predictions within float32 rounding; curvatures equal.
@pytest.mark.parametrize(
    "scene, camera, light_kind, n_lights, bits, noise",
    [
        ("sphere", "orthographic", "directional", 3, 16, 0.0),
        ("sphere", "perspective", "point", 3, 16, 0.0),
        ("bumps", "orthographic", "directional", 8, 16, 0.0),
        ("bumps", "perspective", "directional", 12, 8, 0.01),
        ("sphere", "perspective", "point", 8, 8, 0.01),
    ],
)
def test_device_dgmc_equals_host_on_rendered_scenes(device, scene, camera, light_kind, n_lights, bits, noise):
    img, L, sc, nrm, pts = _scene(scene, 64, camera, light_kind, n_lights, bits, noise)
    # unit-intensity point lights 8 units away: grey values ~1e-2, so the absolute margin scales with them
    cfg = H.DGMCConfig(margin=0.02 * float(np.median(img[:, sc.mask])) / 0.3)
    h = H.dgmc_start(img, sc.mask, nrm, lights=L, points=pts, config=cfg)
    d = dgmc_start_device(img, sc.mask, nrm, lights=L, points=pts, config=cfg, device=device)
    assert h.highlight.sum() > 50  # the scene has highlights to find
    _assert_same(h, d)


@pytest.mark.parametrize("field", ["intensity", "normals"])
def test_device_options_equal_host(device, field):
    """Percentile rule with saturation, 4-connectivity, normals curvature, fewer candidates, grey images."""
    img, L, sc, nrm, _ = _scene("bumps", 48, "orthographic", "directional", 6)
    cfg = H.DGMCConfig(rule="percentile", percentile=95.0, saturation=0.9, connectivity=4, k_nearest=5,
                       curvature_field=field, sigma=1.5, tolerance=0.1, widen_steps=1)
    h = H.dgmc_start(img, sc.mask, nrm, config=cfg)
    d = dgmc_start_device(img, sc.mask, nrm, config=cfg, device=device)
    assert h.highlight.sum() > 20 and h.highlights.saturated.any()
    _assert_same(h, d)
    grey = img.mean(-1)
    cfg = H.DGMCConfig(ratio=1.05)
    h = H.dgmc_start(grey, sc.mask, nrm, lights=L.directions, config=cfg)
    d = dgmc_start_device(grey, sc.mask, nrm, lights=L.directions, config=cfg, device=device)
    _assert_same(h, d)


def test_starts_agree_in_accuracy(device):
    """The quantity RON uses: the start normals on highlight pixels, against ground truth (128^2)."""
    img, L, sc, nrm, _ = _scene("bumps", 128, "orthographic", "directional", 3)
    h = H.dgmc_start(img, sc.mask, nrm, lights=L)
    d = dgmc_start_device(img, sc.mask, nrm, lights=L, device=device)
    c = _compare(h, d, sc.normals, sc.mask)
    assert c["maps_agree"] == 1.0 and c["region_iou"] == 1.0 and c["source_agree"] == 1.0, c
    assert c["maen_device"] == pytest.approx(c["maen_host"], abs=1e-6), c


def test_spikes_on_many_lights_are_flagged_exactly(device):
    """Exact Lambertian pixels under 16 lights with +0.25 spikes on 1-3 observations of some pixels: the O(N)
    downdated test flags exactly the spikes (as the host does), and nothing on clean pixels."""
    rng = np.random.default_rng(5)
    n, h, w = 16, 12, 12
    dirs = ring_directions(n, 35.0)
    th = np.deg2rad(15.0) * np.sqrt(rng.uniform(size=(h, w)))
    ph = rng.uniform(0, 2 * np.pi, (h, w))
    nrm = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    g = 0.5 * np.einsum("kc,hwc->khw", dirs, nrm)
    spike = np.zeros(g.shape, bool)
    for p in rng.choice(h * w, 30, replace=False):
        spike[rng.choice(n, rng.integers(1, 4), replace=False), p // w, p % w] = True
    img = (g + 0.25 * spike).astype(np.float32)
    mask = np.ones((h, w), bool)
    d = dgmc_start_device(img, mask, nrm, lights=dirs, device=device)
    np.testing.assert_array_equal(d.highlights.maps, spike)
    hres = H.dgmc_start(img, mask, nrm, lights=dirs)
    _assert_same(hres, d)


# --------------------------------------------------------------------------- geodesic lists, exactly


def _dijkstra_lists(region, boundary, k):
    """Per region pixel the k nearest boundary pixels by textbook Dijkstra (heapq), with distances kept as exact
    step counts (a, b) and ties by flat index: {(i, j): [(a + b sqrt 2, flat), ...]}."""
    h, w = region.shape
    best = {}
    for q in zip(*np.nonzero(boundary)):
        d = {}
        heap = []
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                v = (q[0] + di, q[1] + dj)
                if (di or dj) and 0 <= v[0] < h and 0 <= v[1] < w and region[v]:
                    heapq.heappush(heap, ((0, 1) if di and dj else (1, 0), v))
        while heap:
            (a, b), u = heapq.heappop(heap)
            if u in d and a + b * math.sqrt(2) >= d[u][0] + d[u][1] * math.sqrt(2) - 1e-12:
                continue
            d[u] = (a, b)
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    v = (u[0] + di, u[1] + dj)
                    if (di or dj) and 0 <= v[0] < h and 0 <= v[1] < w and region[v]:
                        heapq.heappush(heap, ((a, b + 1) if di and dj else (a + 1, b), v))
        for u, (a, b) in d.items():
            best.setdefault(u, []).append((a + b * math.sqrt(2), q[0] * w + q[1]))
    return {u: sorted(v, key=lambda t: (round(t[0], 9), t[1]))[:k] for u, v in best.items()}


def _blob_case(seed, h=14, w=17):
    """Random regions (blobs with holes, several components, some touching the mask's edge) as exact spikes on
    Lambertian pixels, so the device stage finds exactly them."""
    from scipy import ndimage as ndi

    rng = np.random.default_rng(seed)
    region = ndi.binary_opening(rng.uniform(size=(h, w)) < 0.55, np.ones((2, 2), bool)) | (rng.uniform(size=(h, w)) < 0.05)
    mask = np.ones((h, w), bool)
    mask[:, -2:] = False
    mask[rng.integers(0, h), :] = False
    region &= mask
    dirs = ring_directions(4, 35.0)
    nrm = np.broadcast_to([0.0, 0.0, 1.0], (h, w, 3)).copy()
    g = 0.5 * np.einsum("kc,hwc->khw", dirs, nrm)
    g[0] += 0.3 * region
    return g.astype(np.float32), mask, region, dirs, nrm


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("connectivity", [8, 4])
def test_geodesic_lists_equal_dijkstra(device, seed, connectivity):
    img, mask, region, dirs, nrm = _blob_case(seed)
    k = 6
    cfg = H.DGMCConfig(connectivity=connectivity, k_nearest=k)
    with DeviceDGMC(img.shape, config=cfg, device=device) as st:
        res = st.run(img, mask, nrm, lights=dirs)
        src, dist = st.candidates()
    np.testing.assert_array_equal(res.highlight, region)
    labels = res.highlights.labels
    assert res.highlights.n_regions >= 2
    for lab in range(1, res.highlights.n_regions + 1):
        reg = labels == lab
        bnd = H.outer_boundary(reg, mask, connectivity)
        pix, s_host, d_host = H.geodesic_candidates(reg, bnd, k)  # scipy's dijkstra
        ref = _dijkstra_lists(reg, bnd, k)  # heapq with exact step counts
        for (i, j), sh, dh in zip(pix, s_host, d_host):
            np.testing.assert_array_equal(src[i, j], sh)
            np.testing.assert_allclose(dist[i, j], dh, rtol=0, atol=1e-12)
            r = ref.get((i, j), [])
            assert [t[1] for t in r] == src[i, j][: len(r)].tolist()
            np.testing.assert_allclose(dist[i, j][: len(r)], [t[0] for t in r], rtol=0, atol=1e-12)
    assert (src[~region] == -1).all()


def test_geodesic_lists_longer_than_the_thread_local_set(device):
    """K above LIST_CAP: the sources past the first LIST_CAP are checked for repeats in the written list (global
    memory) instead of the thread-local set; the lists are still scipy's, on a case with more than K boundary
    pixels per region so that the long lists fill up."""
    from gpps.kernels.dgmc_geodesic import LIST_CAP

    img, mask, region, dirs, nrm = _blob_case(3, h=40, w=46)
    k = LIST_CAP + 12
    with DeviceDGMC(img.shape, config=H.DGMCConfig(k_nearest=k), device=device) as st:
        res = st.run(img, mask, nrm, lights=dirs)
        src, dist = st.candidates()
    np.testing.assert_array_equal(res.highlight, region)
    labels = res.highlights.labels
    full = 0
    for lab in range(1, res.highlights.n_regions + 1):
        reg = labels == lab
        pix, s_host, d_host = H.geodesic_candidates(reg, H.outer_boundary(reg, mask, 8), k)
        for (i, j), sh, dh in zip(pix, s_host, d_host):
            np.testing.assert_array_equal(src[i, j], sh)
            np.testing.assert_allclose(dist[i, j], dh, rtol=0, atol=1e-12)
            full += int(sh[LIST_CAP] >= 0)
    assert full > 50  # many lists run past LIST_CAP


def test_geodesic_corridor(device):
    """A U-shaped corridor of highlight pixels fed from one end: distances follow it (host test's numbers)."""
    mask = np.zeros((3, 6), bool)
    mask[0, :] = mask[2, :] = True
    mask[1, 5] = True
    region = mask.copy()
    region[0, 0] = False
    dirs = ring_directions(4, 35.0)
    nrm = np.broadcast_to([0.0, 0.0, 1.0], (3, 6, 3)).copy()
    img = (0.5 * np.einsum("kc,hwc->khw", dirs, nrm) + 0.3 * region[None] * (np.arange(4) == 1)[:, None, None])
    with DeviceDGMC(img.shape, config=H.DGMCConfig(k_nearest=2), device=device) as st:
        res = st.run(img.astype(np.float32), mask, nrm, lights=dirs)
        src, dist = st.candidates()
    np.testing.assert_array_equal(res.highlight, region)
    r2 = math.sqrt(2.0)
    assert dist[0, 3, 0] == pytest.approx(3.0)
    assert dist[1, 5, 0] == pytest.approx(4 + r2)
    assert dist[2, 4, 0] == pytest.approx(4 + 2 * r2)
    assert dist[2, 0, 0] == pytest.approx(8 + 2 * r2)
    assert (src[region][:, 0] == 0).all() and (src[region][:, 1] == -1).all()
    assert res.source[2, 0].tolist() == [0, 0] and res.distance[2, 0] == pytest.approx(8 + 2 * r2)


# --------------------------------------------------------------------------- the stage's protocol


def test_stage_reuses_its_buffers_and_takes_device_arrays(device):
    from gpps._runtime import warp

    wp = warp()
    img, L, sc, nrm, _ = _scene("sphere", 48, "orthographic", "directional", 3)
    h = H.dgmc_start(img, sc.mask, nrm, lights=L)
    st = DeviceDGMC(img.shape[:3], device=device)
    keys = st.keys[0]
    first = st.run(img, sc.mask, nrm, lights=L)
    dimg = wp.array(img, dtype=wp.vec3, device=st.device)
    dnrm = wp.array(nrm, dtype=wp.vec3d, device=st.device)
    second = st.run(dimg, sc.mask, dnrm, lights=L)
    assert st.keys[0] is keys
    _assert_same(h, first)
    _assert_same(h, second)
    st.close()
    with pytest.raises(RuntimeError, match="closed"):
        st.step()


def test_stage_bad_input_names_the_argument(device):
    img, L, sc, nrm, _ = _scene("sphere", 32, "orthographic", "directional", 3)
    st = DeviceDGMC(img.shape[:3], device=device)
    with pytest.raises(RuntimeError, match="upload"):
        st.step()
    with pytest.raises(ValueError, match=r"^images: expected \(N, H, W\) = \(3, 32, 32\)"):
        st.upload(img[:, :-1], sc.mask, nrm, lights=L)
    with pytest.raises(ValueError, match=r"^images: expected values >= 0"):
        st.upload(-img, sc.mask, nrm, lights=L)
    with pytest.raises(ValueError, match=r"^mask: expected shape \(32, 32\)"):
        st.upload(img, sc.mask[:-1], nrm, lights=L)
    with pytest.raises(ValueError, match=r"^normals: expected unit vectors"):
        st.upload(img, sc.mask, 2 * nrm, lights=L)
    with pytest.raises(ValueError, match=r"^lights: expected .* got None"):
        st.upload(img, sc.mask, nrm)
    with pytest.raises(ValueError, match=r"^lights: expected 3 lights"):
        st.upload(img, sc.mask, nrm, lights=DirectionalLights(ring_directions(4)))
    with pytest.raises(ValueError, match=r"^points: expected"):
        st.upload(img, sc.mask, nrm, lights=PointLights(np.eye(3)))
    with pytest.raises(TypeError, match=r"^config: expected DGMCConfig"):
        DeviceDGMC(img.shape[:3], config={"ratio": 1.1}, device=device)
    with pytest.raises(ValueError, match=r"^shape: expected N >= 3"):
        DeviceDGMC((2, 8, 8), device=device)
    with pytest.raises(ValueError, match=r"^shape: expected H W <= 2\^28 pixels"):
        DeviceDGMC((3, 1 << 14, (1 << 14) + 1), device=device)  # refused before any allocation


def test_step_without_starts_gives_the_front_its_maps_only(device):
    """step(starts=False) (what RON's solved front reads): the highlight region and the curvatures equal the full
    step's (and the host's); no start normals come back and the full result is refused."""
    img, L, sc, nrm, _ = _scene("bumps", 48, "orthographic", "directional", 8)
    h = H.dgmc_start(img, sc.mask, nrm, lights=L)
    st = DeviceDGMC(img.shape[:3], device=device)
    st.upload(img, sc.mask, nrm, lights=L)
    st.step(starts=False)
    part = st.fetch_start()
    assert part.normals is None
    assert h.highlight.sum() > 20
    np.testing.assert_array_equal(part.highlight, h.highlight)
    np.testing.assert_allclose(part.gaussian, h.gaussian, rtol=0, atol=1e-6 * float(np.abs(h.gaussian).max()))
    np.testing.assert_allclose(part.mean, h.mean, rtol=0, atol=1e-6 * float(np.abs(h.mean).max()))
    with pytest.raises(RuntimeError, match="starts=False"):
        st.fetch()
    with pytest.raises(RuntimeError, match="starts=False"):
        st.candidates()
    st.step()  # the full step again: everything as the host's
    _assert_same(h, st.fetch())
    full = st.fetch_start()
    np.testing.assert_array_equal(full.highlight, part.highlight)
    np.testing.assert_array_equal(full.gaussian, part.gaussian)
    st.close()


def test_solver_normals_taken_on_the_device(device):
    """upload() with a solve's float32 normals (a Warp vec3 array, as RON passes PixelSolver.normals): converted on
    the device by RON's former host rule (float64; (0, 0, 1) where the normal is not unit within 1e-3 or outside
    the mask), so the stage's normals and its whole result equal an upload of that rule's numpy normals; the
    curvatures can stay on the device (fetch_start(curvatures=False))."""
    import warp as wp

    img, L, sc, _, _ = _scene("bumps", 48, "orthographic", "directional", 8)
    rng = np.random.default_rng(3)
    n32 = np.zeros(sc.mask.shape + (3,), np.float32)
    v = rng.normal(size=(int(sc.mask.sum()), 3)) + (0.0, 0.0, 3.0)
    n32[sc.mask] = (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)
    ys, xs = np.nonzero(sc.mask)
    n32[ys[0], xs[0]] = 0.0  # undetermined (zero), not finite, too long, and a unit normal outside the mask
    n32[ys[1], xs[1]] = np.nan
    n32[ys[2], xs[2]] *= 1.01
    n32[~sc.mask] = (0.6, 0.0, 0.8)
    ref = n32.astype(np.float64)  # RON's host rule before the device took it
    with np.errstate(invalid="ignore"):
        ok = sc.mask & (np.abs(np.linalg.norm(ref, axis=-1) - 1.0) < 1e-3)
    ref[~ok] = (0.0, 0.0, 1.0)
    assert (~ok & sc.mask).sum() == 3
    host = DeviceDGMC(img.shape[:3], device=device)
    host.upload(img, sc.mask, ref, lights=L)
    host.step(starts=False)
    want = host.fetch_start()
    st = DeviceDGMC(img.shape[:3], device=device)
    st.upload(img, sc.mask, wp.array(n32, dtype=wp.vec3, device=device), lights=L)
    np.testing.assert_array_equal(st.normals.numpy(), ref)
    st.step(starts=False)
    got = st.fetch_start(curvatures=False)
    assert got.gaussian is None and got.mean is None
    np.testing.assert_array_equal(got.highlight, want.highlight)
    np.testing.assert_array_equal(st.gc.numpy().astype(np.float32), want.gaussian)
    with pytest.raises(ValueError, match=r"^normals: expected a \(48, 48\) vec3d or vec3 array"):
        st.upload(img, sc.mask, wp.zeros((48, 47), dtype=wp.vec3, device=device), lights=L)
    host.close()
    st.close()


def test_kept_stage_takes_a_new_mask(device):
    """The mask's device copies are made once per mask (a kept stage sees one mask frame after frame); a
    different mask, then the first again, give the results of a fresh stage for each."""
    img, L, sc, nrm, _ = _scene("bumps", 48, "orthographic", "directional", 8)
    small = sc.mask.copy()
    small[:, :24] = False
    st = DeviceDGMC(img.shape[:3], device=device)
    for m in (sc.mask, small, sc.mask.copy()):
        fresh = DeviceDGMC(img.shape[:3], device=device)
        fresh.upload(img, m, nrm, lights=L)
        fresh.step()
        st.upload(img, m, nrm, lights=L)
        st.step()
        assert st.count == int(m.sum())
        _assert_same(fresh.fetch(), st.fetch())
        fresh.close()
    st.close()

"""The offline chain's kernels for ``perf/bench.py --chain``: DGMC, the material scorer, the pixel solve, BiNI.

Scene (one for every row, DiLiGenT-ball-like): a perspective sphere (``make_scene("sphere", size,
"perspective", albedo="texture")``), Blinn-Phong (``Material.default_for``: the default model of
``gpps reconstruct``), ``images`` directional lights on a golden-angle spiral (3 images: the ring of
the stream), 16-bit with 0.5 % noise, divided by the light intensities.  Rows (``size``: the image side):

* ``dgmc_step``: :meth:`gpps.pipeline.dgmc.DeviceDGMC.step` (all phases, host syncs included; no
  ratio); ``dgmc_geodesics``: its geodesic phase (reset + sweeps to convergence + checks);
* ``dgmc_highlight``: one launch of :func:`gpps.kernels.dgmc.highlight_kernel` (moments + rank-one
  downdates, every flagging round);
* ``dgmc_geodesic_sweep``: one min-plus sweep (``geodesic_relax_kernel`` with every region pixel active,
  as in the first sweeps; the stage ping-pongs the two list buffers, no copy), from the converged lists: the
  sweep's full work;
* ``dgmc_start_search``: one launch of ``select_kernel`` (4.17-4.18);
* ``scorer_solve_<N>img``: one launch of the material scorer's batched solve
  (:mod:`gpps.kernels.solve_batched`, as :meth:`MaterialScorer.step` launches it) for K candidates x P
  samples, RON's fit config (4 starts, no neighbour pass); ``scorer_step_fetch_<N>img``: ``step`` +
  ``fetch`` as RON calls them (host time, no ratio);
* ``pixel_solve_<N>img``: :meth:`PixelSolver.step` on the whole image with the default
  :class:`SolverConfig` (10 starts, neighbour pass): the offline normals step;
* ``bini_cg_iteration``: one Jacobi-PCG iteration of BiNI (one ``cg`` launch runs ``unroll`` of them;
  time / unroll), float64;
* ``search_trimmed_rank``: one launch of the device material search's trimmed-energy rank kernel
  (:func:`gpps.kernels.material_search.trimmed_rank_kernel`, 4 candidates x P samples x P / RANK_SEGMENT
  segments, P compares an item in all); ``search_pass_no_solve``: a search pass without the scorer's solve (points,
  rank, contributions, partial sums, energy, Nelder-Mead step: :meth:`NelderMeadSearch._pass`'s other six
  launches; no ratio).

Counts (:data:`COUNTS_CHAIN`, by hand per item, documented there).  Unlike the stream's rows, the bytes
are the *compulsory* traffic: every input element read once and every output written once (a
neighbour's value or a re-read of a pixel's own observations counts as a cache hit).  That is the true
lower bound; a kernel whose ratio is far above 1 while it is memory-limited by this count re-reads
through the caches (Nsight Compute's dram / L2 figures of ``perf/ncu_chain.py`` say which).  Work that
depends on the data (flagging rounds, list lengths, candidates checked, cost evaluations per pixel) is
read back from the kernels' own outputs after the timed launches and entered per item.  An integer op or
compare counts as 1 FLOP like an add; the bound of float64 kernels uses the float64 FMA probe.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

# ----------------------------------------------------------------------------- hand counts

# Per-light cost of one solver evaluation (cost, J^T r, J^T J), by bench.COUNTS["iteration"]: a lit light
# (n.l > 0: the lobe, its gradient, diffuse, chart derivatives ~140, 3-channel normal equations ~60), in
# both passes; an unlit one skips the lobe (its gate returns 0): diffuse 15 + chart 12 + gate ~3 + the
# normal equations 60.  Lit is judged at the true normal (the iterates end there).
EVAL_LIT, EVAL_UNLIT, EVAL_FIXED = 2 * (140 + 60), 2 * (30 + 60), 120

COUNTS_CHAIN = {
    # per masked pixel, with f its flagged observations (rounds 0..f, m_r = N - r active):
    # every round scans the N flags in 3 passes (6 N); moments of the active observations 35 each
    # (grey 3, outer product 9 FMA, r 3 FMA, g^2, |s| 6); first eval pass 155 each (downdate 26,
    # 3x3 regularised inverse ~45 and solve 18, prediction 6, residual b^T A b - 2 b.r + G ~32,
    # inconsistency ~15, tests 4); the second pass (only in rounds that flag, r < f) 160 each;
    # plus |s| of every light once (6 N).  Bytes: images 12 N in the mask; flags 1 + predicted 4 per
    # observation and the mask byte everywhere.  Float64.
    "dgmc_highlight": lambda f, n: (
        (12 * n, 6 * n + 6 * n * (f + 1) + 190 * ((f + 1) * n - f * (f + 1) / 2) + 160 * (f * n - (f - 1) * f / 2)),
        (5 * n + 1, 0)),
    # per region pixel with c of its K list entries filled: the activity test (9 reads ~20), 8 slot kinds
    # decoded from one code and their heads (~15 each: key_value, the int64 head order), then c pops, each:
    # best of 8 int64 heads (8), the set probe (~6), store and compare with the old entry (~6), the slot's
    # refresh (~12); repeats passed over at refresh: ~5 per entry kept (8 neighbour lists share most sources;
    # measured ~190 candidates for 32 entries on the 256^2 bumps case), ~12 ops each (load, probe); the
    # K - c empty entries 4 each.  Bytes: the old list read and the new one written (16 K), the neighbours'
    # lists are cache hits; every pixel: slot code 4, changed written 4 (no copy kernel: ping-pong buffers).
    "dgmc_geodesic_sweep": lambda c, k: ((16 * k, 140 + 32 * c + 60 * c + 4 * (k - c)), (8, 0)),
    # per region pixel with a list: L loop steps (list entry loaded, 3 ops) and C full checks (q // w, q % w
    # ~20, GC/MC of the candidate 16 B, 2 abs/sub/mul/compare pairs ~10); the list 4 K once, own GC/MC 16,
    # key 4, normal of the source 24.  Every masked pixel: its normal 24, region 1; every pixel: mask 1 and
    # the outputs 32 (normal 12, source 8, distance 4, rank 4, tolerance 4).
    "dgmc_start_search": lambda lsteps, checks, k: ((4 * k + 16 * checks + 44, 3 * lsteps + 30 * checks + 50),
                                                    (25, 0), (33, 0)),
    # per (candidate, sample): e evaluations of the sample's lit/unlit lights; outputs normal 12, albedo 12,
    # residual, iterations, flags 4 each.  Per sample (once for all candidates): strip 12 N, weights 4 N,
    # point, view, start 12 each, gmax and flags 4 each.
    "scorer_solve": lambda e, lit, n: ((36, e * (EVAL_LIT * lit + EVAL_UNLIT * (n - lit) + EVAL_FIXED)),
                                       (16 * n + 44, 0)),
    # per masked pixel: e evaluations (all starts); images 12 N, valid N, weights written 4 N, depth 4;
    # every pixel: mask 1, outputs 40 (normal, albedo 12 each; residual, iterations, flags, cond 4 each).
    "pixel_solve": lambda e, lit, n: ((17 * n + 4, e * (EVAL_LIT * lit + EVAL_UNLIT * (n - lit) + EVAL_FIXED)),
                                      (41, 0)),
    # per valid pixel and CG iteration (float64): loop 1 reads z, p_old, W_r, W_d, nb (4 int32) and writes q,
    # p_new (64 B; the 4 neighbours' z, p_old, W: cache); fused p = z + beta p_old for itself and 4
    # neighbours and A p (~25 FLOPs), p.q; loop 2 reads x, p_new, r, q, D^-1, writes x, r, z (64 B), 9 FLOPs
    # + 2 sums.
    "bini_cg_iteration": lambda: ((128, 36),),
    # per (candidate, sample): P compares of the sample against every value of its row over its segments (load
    # from cache, NaN key, two compares and an index compare, count: 5 ops each), one atomic add a segment;
    # bytes: its residual read 4 and its int32 count added 4 (the row's other values: cache hits).
    "search_trimmed_rank": lambda p: ((8, 5 * p),),
}


@dataclass
class Ctx:
    """What the chain rows need from bench.py: device, repeat, roofline and its timers."""

    device: str
    repeat: int
    bw: float
    peak: float  # float32 FLOP/s (FMA = 2)
    peak64: float  # float64 FLOP/s
    median_time: Callable
    graph_time: Callable
    size: int
    driver: int = 0  # > 0: no timing; the launches of each kernel for the profiler (launch_profiled)
    launches: list = field(default_factory=list)  # (label, pattern, launch, count, taichi, per_launch)
    rows: list = field(default_factory=list)
    keep: list = field(default_factory=list)  # the stages, alive until the driver's launches are done

    def log(self, s: str) -> None:
        print(s, file=sys.stderr, flush=True)


def _wp():
    from gpps._runtime import warp

    return warp()


def _sync(ctx):
    _wp().synchronize_device(ctx.device)


def row(ctx, name, seconds, by=None, fl=None, f64=False, extra=None):
    """Append a row: ``ratio = seconds / max(by / bw, fl / peak)`` when counts are given."""
    r = {"size": ctx.size, "kernel": name, "seconds": seconds}
    if by is not None:
        peak = ctx.peak64 if f64 else ctx.peak
        bound = max(by / ctx.bw, fl / peak)
        r.update(bytes=float(by), flops=float(fl), gbps=by / seconds / 1e9, gflops=fl / seconds / 1e9,
                 bound_s=bound, ratio=seconds / bound, flop_peak="f64" if f64 else "f32",
                 limited_by="memory" if by / ctx.bw >= fl / peak else "compute")
    if extra:
        r.update(extra)
    ctx.rows.append(r)
    ctx.log(f"[chain {ctx.size}] {name:26s} {seconds * 1e3:10.4f} ms"
            + (f"  ratio {r['ratio']:.2f} ({r['limited_by']})" if "ratio" in r else ""))
    return r


def ball_scene(size, n_images, device):
    """The chain's scene: ``(scene, material, unit-intensity lights, (N, H, W, 3) float32 images)``."""
    from gpps.flows.synthetic import default_lights, render
    from gpps.host.scenes import make_scene
    from gpps.lights import DirectionalLights
    from gpps.material import Material

    sc = make_scene("sphere", size, "perspective", albedo="texture")
    mat = Material.default_for("blinn-phong")
    L = default_lights("directional", n_images, layout="ring" if n_images <= 3 else "spiral")
    img = render(sc, mat, L, bits=16, noise=0.005, device=device)
    img = (img / np.asarray(L.intensities, np.float32)[:, None, None, :]).astype(np.float32)
    return sc, mat, DirectionalLights(L.directions), img


def lit_count(normals, directions):
    """Lights with n.l > 0 at each of the given (M, 3) normals: (M,) int."""
    return (np.asarray(normals, np.float64) @ np.asarray(directions, np.float64).T > 0).sum(1)


def _time_or_register(ctx, label, pattern, launch, inner=20, taichi=False, per_launch=1):
    """Device time of one ``launch`` (CUDA graph of ``inner`` on CUDA), or, in driver mode, register it.

    ``pattern``: a regular expression matching the names of the kernels ``launch`` runs (``per_launch`` of
    them; None: unknown, Taichi's tasks) for perf/ncu_chain.py.
    """
    if ctx.driver:
        launch()  # compile / load now, outside the profiled range
        ctx.launches.append((label, pattern, launch, ctx.driver, taichi, per_launch))
        return None
    if taichi:
        from gpps._taichi import ti

        return ctx.median_time(launch, ti.sync, ctx.repeat, inner=inner)
    return ctx.graph_time(_wp(), launch, ctx.device, ctx.repeat, inner=inner)


# ----------------------------------------------------------------------------- DGMC


def dgmc_rows(ctx, n_images):
    """DGMC on the device: the whole step and its geodesic phase, then the three kernels one launch each."""
    from gpps.kernels import dgmc as dk
    from gpps.kernels import dgmc_geodesic as dg
    from gpps.pipeline.dgmc import DeviceDGMC

    wp = _wp()
    t0 = time.perf_counter()
    sc, _, lights, img = ball_scene(ctx.size, n_images, ctx.device)
    m = sc.mask
    nrm = np.where(m[..., None], sc.normals, (0.0, 0.0, 1.0)).astype(np.float64)
    st = DeviceDGMC(img.shape[:3], device=ctx.device)
    st.upload(img, m, nrm, lights=lights)
    st.step()
    _sync(ctx)
    ctx.log(f"[chain {ctx.size}] DGMC {n_images} images: scene, compile and first step {time.perf_counter() - t0:.1f}s")
    n, h, w = st.shape
    cfg = st.config
    region = st.region.numpy().astype(bool)
    flags = st.flags.numpy().astype(np.int64).sum(0)
    info = {"images": n, "highlight_pixels": int(region.sum()), "mask_pixels": int(m.sum()),
            "flagged_observations": int(flags.sum()), "geodesic_sweeps": int(st.sweeps), "k_nearest": int(cfg.k_nearest)}
    if not ctx.driver:
        reps = max(3, ctx.repeat // 4)
        info["summary"] = f"{st.sweeps} sweeps, {info['highlight_pixels']} highlight px"
        row(ctx, "dgmc_step", ctx.median_time(st.step, lambda: _sync(ctx), reps, warmup=1), extra=dict(info))
        row(ctx, "dgmc_geodesics", ctx.median_time(st._geodesics, lambda: _sync(ctx), reps, warmup=1),
            extra={**info, "note": "reset + sweeps to convergence, a host check every 8 sweeps"})

    light = [st.light_kind, st.lvec, st.laxis, st.lmu, st.lint, st.points]

    def highlight():
        wp.launch(dk.highlight_kernel, dim=(h, w),
                  inputs=[st.images, st.channels, st.mask, *light, st.rho, float(cfg.ratio), float(cfg.margin),
                          st.flags, st.predicted], device=ctx.device)

    t = _time_or_register(ctx, "dgmc_highlight", "highlight_kernel", highlight, inner=5)
    if t is not None:
        f = flags[m]
        (pb, pf), (ab, _) = COUNTS_CHAIN["dgmc_highlight"](f.astype(np.float64), n)
        row(ctx, "dgmc_highlight", t, pb * f.size + ab * h * w, float(np.sum(pf)), f64=True,
            extra={**info, "mean_rounds": float(np.mean(f + 1)),
                   "summary": f"{np.mean(f + 1):.2f} rounds/px, {int(f.sum())} flags"})

    def sweep():  # reads the converged lists (keys[0]) and writes the same lists into keys[1]
        wp.launch(dg.geodesic_relax_kernel, dim=(h, w),
                  inputs=[st.slots, 1, st.keys[0], st.srcs[0], st.changed[0], st.keys[1], st.srcs[1], st.changed[1],
                          st.counter, 0, 0], device=ctx.device)

    t = _time_or_register(ctx, "dgmc_geodesic_sweep", "geodesic_relax_kernel", sweep, inner=10)
    srcs = st.srcs[0].numpy()
    k = srcs.shape[2]
    filled = (srcs >= 0).sum(-1)
    if t is not None:
        c = filled[region].astype(np.float64)
        (rb, rf), (ab, _) = COUNTS_CHAIN["dgmc_geodesic_sweep"](c, k)
        changed = int(st.counter.numpy()[0])
        row(ctx, "dgmc_geodesic_sweep", t, rb * c.size + ab * h * w, float(np.sum(rf)),
            extra={**info, "region_pixels": int(c.size), "mean_list_length": float(c.mean()) if c.size else 0.0,
                   "changed_in_timed_sweeps": changed,
                   "summary": f"{c.size} region px, lists {c.mean() if c.size else 0:.1f}/{k}",
                   "note": "every region pixel active (first-sweep work) on the converged lists; one relax launch"})

    def select():
        st._select()

    t = _time_or_register(ctx, "dgmc_start_search", "select_kernel", select, inner=10)
    if t is not None:
        rank = st.rank.numpy()
        tol = st.tol_used.numpy().astype(np.float64)
        has = region & (srcs[..., 0] >= 0)
        found = np.isfinite(tol[has])
        steps = np.full(found.shape, cfg.widen_steps + 1, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.round(np.log(tol[has] / cfg.tolerance) / np.log(cfg.widen_factor))
        steps[found] = s[found]
        c = filled[has].astype(np.float64)
        lsteps = np.where(found, k * (steps + 1), k * (cfg.widen_steps + 1))
        checks = np.where(found, steps * c + rank[has] + 1, (cfg.widen_steps + 1) * c)
        (lb, lf), (mb, _), (ab, _) = COUNTS_CHAIN["dgmc_start_search"](lsteps, checks, k)
        row(ctx, "dgmc_start_search", t, float(np.sum(lb)) + mb * int(m.sum()) + ab * h * w, float(np.sum(lf)),
            extra={**info, "searching_pixels": int(has.sum()), "mean_checks": float(checks.mean()) if checks.size else 0.0,
                   "found_within_tolerance": float(found.mean()) if found.size else 0.0,
                   "summary": f"{int(has.sum())} px, {checks.mean() if checks.size else 0:.1f} checks/px"})
    ctx.keep.append(st)


# ----------------------------------------------------------------------------- material scorer


def _candidates(mat, k):
    """k Blinn-Phong candidates on a log grid over ks and shininess (RON's ranges), row by row."""
    from gpps.material import Material

    g = int(np.ceil(np.sqrt(k)))
    ks = np.exp(np.linspace(np.log(0.02), np.log(3.0), g))
    sh = np.exp(np.linspace(np.log(2.0), np.log(500.0), g))
    out = []
    for a in ks:
        for b in sh:
            d = mat.to_dict()
            d["ks"], d["shininess"] = float(a), float(b)
            out.append(Material.from_dict(d))
    return out[:k]


def _sample_scorer(ctx, n_images, samples, n_cand, *, seed=0, parallel=None):
    """The chain scene, a random sample of ``samples`` mask pixels and a :class:`MaterialScorer` with RON's fit
    config (4 starts, no neighbour pass) holding it: ``(scene, material, lights, images, scorer, P)``."""
    from gpps.pipeline.material import MaterialScorer
    from gpps.pipeline.solver import SolverConfig

    sc, mat, lights, img = ball_scene(ctx.size, n_images, ctx.device)
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(sc.mask.ravel())
    sample = np.zeros(sc.mask.size, bool)
    sample[rng.choice(idx, min(samples, idx.size), replace=False)] = True
    sample = sample.reshape(sc.mask.shape)
    p = int(sample.sum())
    fit = replace(SolverConfig(), starts=4, neighbour_radius=0, smoothness=0.0, warm_start=False)  # RON's fit
    kw = {} if parallel is None else {"parallel": parallel}
    scorer = MaterialScorer(img.shape[:3], sc.camera, lights, mat, fit, max_samples=p, max_candidates=n_cand,
                            device=ctx.device, **kw)
    scorer.upload(img, sample)
    return sc, mat, lights, img, scorer, p


def scorer_rows(ctx, n_images, samples, n_cand):
    """The material scorer's batched solve: one launch of K candidates x P samples."""
    wp = _wp()
    t0 = time.perf_counter()
    sc, mat, lights, img, scorer, p = _sample_scorer(ctx, n_images, samples, n_cand)
    cands = _candidates(mat, n_cand)
    scorer.step(cands)
    energies = scorer.fetch()
    _sync(ctx)
    ctx.log(f"[chain {ctx.size}] scorer {n_images} images, K={n_cand}, P={p}: compile and first step "
            f"{time.perf_counter() - t0:.1f}s")
    name = f"scorer_solve_{n_images}img"

    def launch():
        wp.launch(scorer._kernel, dim=(n_cand, p),
                  inputs=[scorer._strip_k, scorer.base_weights, scorer.points, scorer.views, scorer.ninit,
                          scorer.gmax, scorer.flags, scorer.lp, scorer.mats, scorer.prm, 0],
                  outputs=[scorer._weights_k, scorer.normals, scorer.albedo, scorer.residual, scorer.iterations,
                           scorer.flags_k], device=ctx.device)

    t = _time_or_register(ctx, name, "solve_batched_kernel", launch, inner=3)
    if t is not None:
        ev = scorer.iterations.numpy()[:n_cand, :p].astype(np.float64)
        lit = lit_count(sc.normals[scorer.rows_host, scorer.cols_host], lights.directions)
        (cb, cf), (sb, _) = COUNTS_CHAIN["scorer_solve"](ev, lit[None, :], n_images)
        info = {"images": n_images, "candidates": n_cand, "samples": p, "mean_evaluations": float(ev.mean()),
                "mean_lit": float(lit.mean()), "energy_min": float(np.min(energies)),
                "summary": f"K={n_cand} P={p}, {ev.mean():.1f} evaluations/item"}
        row(ctx, name, t, cb * ev.size + sb * p, float(np.sum(cf)), extra=info)
        th = ctx.median_time(lambda: (scorer.step(cands), scorer.fetch()), lambda: _sync(ctx), ctx.repeat)
        row(ctx, f"scorer_step_fetch_{n_images}img", th,
            extra={**info, "note": "MaterialScorer.step + fetch (host time, candidates uploaded, energies back)"})
    ctx.keep.append(scorer)


def scorer_lanes_rows(ctx, n_images, samples=500, n_cand=4):
    """The scorer's lights-parallel build (``parallel="lights"``: one 32-lane block a (candidate, pixel)
    solve), at the size where ``"auto"`` picks it: a later round's K x P <= 500 x N solves."""
    t0 = time.perf_counter()
    sc, mat, lights, img, scorer, p = _sample_scorer(ctx, n_images, samples, n_cand, seed=1, parallel="lights")
    cands = _candidates(mat, n_cand)
    scorer.set_candidates(cands)
    scorer.launch()
    energies = scorer.fetch()
    _sync(ctx)
    ctx.log(f"[chain {ctx.size}] lanes scorer {n_images} images, K={n_cand}, P={p}: compile and first step "
            f"{time.perf_counter() - t0:.1f}s")
    name = f"scorer_solve_{n_images}img_lanes"
    t = _time_or_register(ctx, name, "solve_batched_kernel", scorer.launch, inner=3)
    if t is not None:
        ev = scorer.iterations.numpy()[:n_cand, :p].astype(np.float64)
        lit = lit_count(sc.normals[scorer.rows_host, scorer.cols_host], lights.directions)
        (cb, cf), (sb, _) = COUNTS_CHAIN["scorer_solve"](ev, lit[None, :], n_images)
        info = {"images": n_images, "candidates": n_cand, "samples": p, "lanes": 32,
                "mean_evaluations": float(ev.mean()), "mean_lit": float(lit.mean()),
                "energy_min": float(np.min(energies)),
                "summary": f"K={n_cand} P={p} x 32 lanes, {ev.mean():.1f} evaluations/item",
                "note": "the same work as the one-thread build (its bytes and FLOPs), spread over 32 lanes"}
        row(ctx, name, t, cb * ev.size + sb * p, float(np.sum(cf)), extra=info)
    ctx.keep.append(scorer)


def pixel_solve_lanes_rows(ctx, n_images, pixels=500):
    """PixelSolver's lights-parallel build on a DGMC-front-sized subset (a ring of ~``pixels`` pixels)."""
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    t0 = time.perf_counter()
    sc, mat, lights, img = ball_scene(ctx.size, n_images, ctx.device)
    h, w = sc.mask.shape
    yy, xx = np.mgrid[:h, :w]
    rad = np.hypot(yy - (h - 1) / 2, xx - (w - 1) / 2)
    ring = sc.mask & (np.abs(rad - 0.3 * h) < max(1.0, pixels / (4 * np.pi * 0.3 * h)))
    ps = PixelSolver(img.shape[:3], sc.camera, lights, mat, replace(SolverConfig(), parallel="lights"),
                     device=ctx.device)
    ps.upload(img, sc.mask)
    ps.set_mask(ring)
    ps.step()
    _sync(ctx)
    ctx.log(f"[chain {ctx.size}] lanes pixel solve {n_images} images, {int(ring.sum())} px: compile and first "
            f"solve {time.perf_counter() - t0:.1f}s")
    name = f"pixel_solve_{n_images}img_lanes"
    t = _time_or_register(ctx, name, "(solve|underdetermined)_kernel", ps.step, inner=2, per_launch=2)
    if t is not None:
        out = ps.fetch(("normals", "iterations"))
        ev = out["iterations"][ring].astype(np.float64)
        lit = lit_count(sc.normals[ring], lights.directions)
        (pb, pf), (ab, _) = COUNTS_CHAIN["pixel_solve"](ev, lit, n_images)
        row(ctx, name, t, pb * ev.size + ab * h * w, float(np.sum(pf)),
            extra={"images": n_images, "mask_pixels": int(ev.size), "lanes": 32,
                   "mean_evaluations": float(ev.mean()), "mean_lit": float(lit.mean()),
                   "summary": f"{int(ev.size)} px x 32 lanes, {ev.mean():.1f} evaluations/px",
                   "note": "solve_kernel (lights-parallel) + underdetermined_kernel on a ring subset"})
    ctx.keep.append(ps)


# ----------------------------------------------------------------------------- full-image pixel solve


def pixel_solve_rows(ctx, n_images):
    """The offline normals step: PixelSolver.step over the whole image, default config."""
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    t0 = time.perf_counter()
    sc, mat, lights, img = ball_scene(ctx.size, n_images, ctx.device)
    ps = PixelSolver(img.shape[:3], sc.camera, lights, mat, SolverConfig(), device=ctx.device)
    ps.upload(img, sc.mask)
    ps.step()
    _sync(ctx)
    ctx.log(f"[chain {ctx.size}] pixel solve {n_images} images: compile and first solve {time.perf_counter() - t0:.1f}s")
    name = f"pixel_solve_{n_images}img"
    # the kernels ps.step launches: the cold solve (solve_kernel, its lights-parallel form solve_kernel_lanes, or
    # where it runs starts-parallel, CUDA's default, three launches: prelude, one thread a start, pick and store),
    # then the neighbour pass (underdetermined_kernel, or its three starts-parallel launches where the solve's
    # config would run starts-parallel)
    lanes, split = ps._uses_lanes(), ps._uses_split()
    pattern = "(solve|underdetermined|split_(prelude|starts|finish)|under_(prelude|starts|finish))_kernel"
    launches = (1 if lanes or not split else 3) + (3 if split else 1)
    what = " + ".join([("solve_kernel_lanes" if lanes else "split_prelude/starts/finish_kernel" if split
                        else "solve_kernel"),
                       ("under_prelude/starts/finish_kernel" if split else "underdetermined_kernel")
                       + " (the neighbour pass)"])
    t = _time_or_register(ctx, name, pattern, ps.step, inner=2, per_launch=launches)
    if t is not None:
        from gpps.host.metrics import normal_errors

        out = ps.fetch(("normals", "iterations"))
        m = sc.mask
        ev = out["iterations"][m].astype(np.float64)
        lit = lit_count(sc.normals[m], lights.directions)
        (pb, pf), (ab, _) = COUNTS_CHAIN["pixel_solve"](ev, lit, n_images)
        h, w = m.shape
        row(ctx, name, t, pb * ev.size + ab * h * w, float(np.sum(pf)),
            extra={"images": n_images, "mask_pixels": int(ev.size), "mean_evaluations": float(ev.mean()),
                   "mean_lit": float(lit.mean()), "maen_deg": normal_errors(out["normals"], sc.normals, m)["mean"],
                   "summary": f"{ev.mean():.1f} evaluations/px",
                   "note": f"{what}, default SolverConfig"})
    ctx.keep.append(ps)


# ----------------------------------------------------------------------------- BiNI


def bini_rows(ctx):
    """One Jacobi-PCG iteration of BiNI (Taichi, float64) on the sphere's true normals."""
    from gpps._taichi import ti
    from gpps.host.scenes import make_scene
    from gpps.pipeline.integration_bini import BilateralIntegrator

    t0 = time.perf_counter()
    sc = make_scene("sphere", ctx.size, "perspective")
    bi = BilateralIntegrator(sc.mask, sc.camera, device="cuda:0" if ctx.device.startswith("cuda") else "cpu")
    bi.upload(sc.normals)
    F = bi._F
    kn = F["kernels"]
    n = bi.n
    unroll = int(F["unroll"])
    kn["begin"](n)

    def cg():  # tol 0: never done, every launch runs all its iterations
        kn["cg"](n, 0.0, 1 << 30)

    cg()
    ti.sync()
    ctx.log(f"[chain {ctx.size}] BiNI: compile and first CG launch {time.perf_counter() - t0:.1f}s")
    t = _time_or_register(ctx, "bini_cg_iteration", "^cg", cg, inner=10, taichi=True, per_launch=None)
    if t is not None:
        ((b, f),) = COUNTS_CHAIN["bini_cg_iteration"]()
        ws = n * (18 * 8 + 6 * 4)  # 18 float64 fields, nb and pix
        row(ctx, "bini_cg_iteration", t / unroll, b * n, f * n, f64=True,
            extra={"pixels": n, "iterations_per_launch": unroll, "working_set_bytes": ws,
                   "summary": f"{n} px, working set {ws / 1e6:.2f} MB",
                   "note": "one cg launch / unroll (tol 0: all iterations run); Taichi, float64; a working set "
                           "that fits in the last-level cache can beat the DRAM copy bound (ratio < 1)"})
    ctx.keep.append(bi)


PARTS = ("dgmc", "scorer", "solve", "lanes", "bini", "search")


def search_rows(ctx, samples):
    """The device material search's own kernels (3 images: RON's 256^2 x 3 case), around a filled scorer."""
    from gpps.kernels import material_search as ms
    from gpps.pipeline.material_search import NelderMeadSearch

    wp = _wp()
    sc, mat, lights, img, scorer, p = _sample_scorer(ctx, 3, samples, 8)
    scorer.step(_candidates(mat, ms.SEARCH_POINTS))
    search = NelderMeadSearch(scorer, 1)
    x0 = np.log([mat.shininess])
    search.upload(mat, ("shininess",), np.array([x0, x0 + 0.1]), np.array([1.0, 2.0]), lo=np.log([2.0]),
                  hi=np.log([500.0]), maxfev=10 ** 9, xatol=0.0)
    keep = max(1, int(round(p * (1.0 - float(scorer.trim)))))
    kc = ms.SEARCH_POINTS

    seg = ms.RANK_SEGMENT

    def rank():  # (the counts accumulate over the timed launches: the work is the same)
        wp.launch(ms.trimmed_rank_kernel, dim=(kc, p, (p + seg - 1) // seg), inputs=[scorer.residual, p, seg],
                  outputs=[search.before], device=ctx.device)

    t = _time_or_register(ctx, "search_trimmed_rank", "trimmed_rank_kernel", rank, inner=20)
    if t is not None:
        ((cb, cf),) = COUNTS_CHAIN["search_trimmed_rank"](p)
        row(ctx, "search_trimmed_rank", t, cb * kc * p, float(cf * kc * p),
            extra={"candidates": kc, "samples": p, "summary": f"K={kc} P={p}, {p} compares/item"})

    def rest():  # the pass less the scorer's solve (the condition stays set: xatol 0, no budget)
        wp.launch(ms.search_points_kernel, dim=kc,
                  inputs=[search.sim, 1, search.lo, search.hi, search.fields, search.base, search.state],
                  outputs=[search.cand, scorer.mats], device=ctx.device)
        rank()
        wp.launch(ms.trimmed_contrib_kernel, dim=(kc, p), inputs=[scorer.residual, keep],
                  outputs=[search.before, search.contrib], device=ctx.device)
        wp.launch(ms.trimmed_partial_kernel, dim=(kc, ms.PARTIAL_LANES), inputs=[search.contrib, p],
                  outputs=[search.partial], device=ctx.device)
        wp.launch(ms.trimmed_energy_kernel, dim=kc, inputs=[search.partial, keep], outputs=[search.energy],
                  device=ctx.device)
        wp.launch(ms.search_step_kernel, dim=1, inputs=[search.energy, search.cand, 1, 10 ** 9, wp.float64(0.0)],
                  outputs=[search.sim, search.fsim, search.state, search.cond], device=ctx.device)

    if not ctx.driver:
        t = ctx.graph_time(wp, rest, ctx.device, ctx.repeat, inner=10)
        row(ctx, "search_pass_no_solve", t, extra={"candidates": kc, "samples": p,
                                                   "note": "five launches of a search pass without the solve"})
    ctx.keep.extend([search, scorer])


def bench_chain(ctx, parts, images, samples, candidates, errors):
    """All chain rows of ``parts`` (each part's failure is recorded in ``errors`` and the others go on)."""
    import traceback

    jobs = {
        "dgmc": lambda: dgmc_rows(ctx, images),
        "scorer": lambda: [scorer_rows(ctx, n, samples, candidates) for n in dict.fromkeys((images, 3))],
        "solve": lambda: pixel_solve_rows(ctx, images),
        "lanes": lambda: (scorer_lanes_rows(ctx, images), pixel_solve_lanes_rows(ctx, images)),
        "bini": lambda: bini_rows(ctx),
        "search": lambda: search_rows(ctx, samples),
    }
    for part in parts:
        try:
            jobs[part]()
        except Exception as e:  # noqa: BLE001 - keep the other parts' numbers
            errors.append({"size": ctx.size, "part": part, "error": repr(e), "trace": traceback.format_exc()})
            ctx.log(f"[chain {ctx.size}] {part} FAILED: {e!r}")
    return ctx.rows


def launch_profiled(ctx):
    """Driver mode: each registered kernel ``ctx.driver`` times inside one CUDA profiler range, synchronised
    after each; returns the manifest (label, name pattern, launches, in launch order) for perf/ncu_chain.py."""
    wp = _wp()
    cuda = ctx.device.startswith("cuda")
    manifest = []

    def sync(taichi):
        if taichi:
            from gpps._taichi import ti

            ti.sync()
        else:
            _sync(ctx)

    _sync(ctx)
    if any(entry[4] for entry in ctx.launches):
        sync(True)
    if cuda:
        wp.cuda_profiler_start(ctx.device)
    try:
        for label, pattern, launch, count, taichi, per_launch in ctx.launches:
            ctx.log(f"[driver] {label}: {count} launch(es)")
            for _ in range(count):
                launch()
                sync(taichi)
            manifest.append({"label": label, "pattern": pattern, "launches": count, "taichi": bool(taichi),
                             "kernels": None if per_launch is None else count * per_launch})
    finally:
        if cuda:
            wp.cuda_profiler_stop(ctx.device)
    return manifest

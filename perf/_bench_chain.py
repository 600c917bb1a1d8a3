"""The offline chain's kernels for ``perf/bench.py --chain``: DGMC, the material scorer, the pixel solve, BiNI,
the material search, DGMC's solved front, RON's device rounds.

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
* the step's other kernels, one launch each (outputs into scratch arrays where a launch would change what another
  row reads): ``dgmc_start_normals`` (``start_normals_kernel``: :meth:`DeviceDGMC.upload`'s conversion of a solve's
  float32 normals, as RON uploads its solver's), ``dgmc_albedo_sample`` (``albedo_sample_kernel``, the reference
  albedo's sample) and ``dgmc_median`` (``median_kernel``, one thread; the radix sort between them is Warp's: no
  row), ``dgmc_saturation``
  (``saturation_kernel``), the curvatures (4.16): ``dgmc_field`` (``field_kernel``), ``dgmc_correlate_i`` /
  ``dgmc_correlate_j`` (one ``correlate_kernel`` pass along each axis; a step runs 6, or 8 for the normals' field)
  and ``dgmc_curvature`` (``curvature_kernel``); the regions: ``dgmc_label_init``, ``dgmc_label_min`` (one step at
  the fixed point), ``dgmc_roots``, ``dgmc_label_number`` (the labels' scan between them is Warp's: no row),
  ``dgmc_boundary``; the geodesics' set-up: ``dgmc_list_reset`` (one of two a step) and ``dgmc_geodesic_slots``;
* ``scorer_solve_<N>img``: one launch of the material scorer's batched solve
  (:mod:`gpps.kernels.solve_batched`, as :meth:`MaterialScorer.step` launches it) for K candidates x P
  samples, RON's fit config (4 starts, no neighbour pass); ``scorer_step_fetch_<N>img``: ``step`` +
  ``fetch`` as RON calls them (host time, no ratio); ``scorer_starts_<N>img`` where the scorer runs its cold
  solves starts-parallel (CUDA): one :meth:`MaterialScorer.launch` of that build (``solve_starts_kernel``, one
  thread a start, and ``solve_finish_kernel``, the pick), RON's first-round grid; the sample's kernels, one launch
  each, on a sample gathered from a least-squares ``PixelSolver``'s frame as RON does:
  ``scorer_gather_samples_<N>img`` (``gather_samples_kernel``, :meth:`MaterialScorer.upload_from`),
  ``scorer_prepare_samples_<N>img`` (``prepare_samples_kernel``, the sample's material-free terms) and
  ``scorer_gather_start_<N>img`` (``gather_start_kernel``, :meth:`MaterialScorer.set_start` with ``frame``);
* ``pixel_solve_<N>img`` (N = ``images`` and 3: the 256^2 x 3 case's build, starts-parallel on CUDA):
  :meth:`PixelSolver.step` on the whole image with the default :class:`SolverConfig` (10 starts, neighbour
  pass): the offline normals step; ``pixel_solve_warm_<N>img``: RON's warm rounds (``RON._solve(..., cold=False)``:
  that config with ``warm_start=True, starts=1``, the neighbour pass kept; never starts-parallel) from the solver's
  own cold normals: :meth:`PixelSolver.step` (``solve_kernel`` and ``underdetermined_kernel``);
  ``least_squares_<N>img``: RON's first step, Woodham's least squares
  (``PixelSolver`` with solver ``"none"``): one launch of its ``solve_kernel`` over the image (the CPU's row split
  left out); ``merge_saved`` (3 images): one ``merge_saved_kernel`` launch over the image
  (:meth:`PixelSolver.merge_saved` after ``save``, the cold solve, and a warm solve of the mask, as RON's cold
  rounds with start normals);
* ``bini_cg_iteration``: one Jacobi-PCG iteration of BiNI (one ``cg`` launch runs ``unroll`` of them;
  time / unroll), float64;
* ``search_trimmed_rank``: one launch of the device material search's trimmed-energy rank kernel
  (:func:`gpps.kernels.material_search.trimmed_rank_kernel`, 4 candidates x P samples x P / RANK_SEGMENT
  segments, P compares an item in all); ``search_pass_no_solve``: a search pass without the scorer's solve (points,
  rank, contributions, partial sums, energy, Nelder-Mead step: :meth:`NelderMeadSearch._pass`'s other six
  launches; no ratio); the pass's other kernels one launch each: ``search_points`` (``search_points_kernel``, one
  thread a candidate), ``search_contrib`` (``trimmed_contrib_kernel``), ``search_partial``
  (``trimmed_partial_kernel``), ``search_energy`` (``trimmed_energy_kernel``) and ``search_step``
  (``search_step_kernel``, one thread; xatol -1: every timed launch a whole pass);
* DGMC's solved front as RON runs it (least squares, DGMC's highlights and curvatures, the cold solve, then
  :func:`gpps.pipeline.front.propagate_front_device` on a :class:`DeviceFront`): ``front_step``:
  :meth:`DeviceFront.step` (the sources, then per ring mask, starts, warm solve and merge; no ratio);
  ``front_curvature_in``: :meth:`DeviceFront.upload`'s two ``curvature_in_kernel`` launches (GC and MC);
  ``front_source``: one ``front_source_kernel`` over every ring pixel; on the largest ring one launch each of
  ``scatter_mask_kernel`` (``front_scatter_mask``), ``front_start_kernel`` (``front_start``) and
  ``front_merge_kernel`` (``front_merge``, keep_better on the merged ring); ``front_write_back`` (over the
  image) and ``front_source_normals`` (every ring pixel); the rings' solves are the pixel solve's kernels;
* RON's device rounds (:class:`gpps.pipeline.ron_rounds.DeviceRounds`, on the default full-image solve):
  ``rounds_sums``: one ``round_sums_kernel`` (the round's energy and normal change, float64);
  ``rounds_integrate``: :meth:`DeviceRounds.integrate`, the final depth on the device (RON's rounds'
  integrator: multigrid, ``"normal"`` weighting, tol 1e-5; no ratio); ``rounds_pcg_iteration``: one fused
  ``pcg_iteration`` launch of its PCG (:func:`gpps.kernels.poisson.pcg_iteration`: cg_step, the V-cycle over
  every level, cg_direction; Taichi, float32 fields); the integration's other Taichi calls, each timed on its own
  as :class:`gpps.pipeline.integration_rounds.DeviceSystem` makes it: ``rounds_assemble_pixels``
  (``assemble_pixels``), ``rounds_assemble_edges`` (``assemble_edges``), ``rounds_coarsen`` (``coarsen``, every
  level's call), ``rounds_gather_level`` (``gather_level``), ``rounds_residual_norm`` (``residual_norm``: the CG
  start's |b|^2), ``rounds_pcg_start`` (the fused ``pcg_start``), then after the CG ``rounds_component_sums``,
  ``rounds_depth_exp`` (perspective), ``rounds_depth_write`` and ``rounds_depth_fill`` (Taichi's own field fills
  and copies, and the labelling of dropped normals, which the ball does not run: no rows).

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
    # The rest of DeviceDGMC.step's kernels (gpps.kernels.dgmc, gpps.kernels.dgmc_geodesic; one thread a pixel unless
    # said; Warp's `and` short-circuits, so an operand past a false one is neither read nor computed).
    # albedo_sample_kernel (the reference albedo's sample), per pixel: mask 1 read, the flat index (2) written as the
    # value 4 and the key 8 (inf outside); per mask pixel: its N observations 12 N read; per light: the grey value
    # (3 widenings, 2 adds, a division, the channel test: 7), the moments s s^T (9 mul + 9 add) and r += g s (3 FMA:
    # 6), the light vector's kind test 1: 32; then the regularised 3x3 solve (eps added 9, inverse ~54, A^-1 r 15)
    # and |b| (6): 84.  Float64.
    "dgmc_albedo_sample": lambda n: ((12 * n, 32 * n + 84), (13, 4)),
    # start_normals_kernel (DeviceDGMC.upload of a solve's float32 normals), per pixel: the normal 12 and mask 1 read,
    # the float64 normal 24 written; 3 widenings, the mask and ok tests 2; per mask pixel: the length (3 mul, 2 add,
    # sqrt: 6), the sub, abs and compare 3.  Float64.
    "dgmc_start_normals": lambda: ((37, 5), (0, 9)),
    # median_kernel: one thread, the middle two of the sorted keys 16 B read, rho 8 written; halving, parity test,
    # add, divide: ~5.
    "dgmc_median": lambda: ((24, 5),),
    # saturation_kernel, per pixel and light: the `use` test 1, the flag 1 B read and tested 1, the saturated byte
    # 1 B written; the region byte 1 B written a pixel.  With `use` (DGMCConfig.saturation set), per mask pixel and
    # light: the observation 12 B, mask 1 B (a cache hit after the first light), the channel max 2, widening,
    # compare: 4 more FLOPs (the flags a saturated observation sets not counted).
    "dgmc_saturation": lambda n, use: ((2 * n + 1 + (1 if use else 0), 2 * n), ((12 * n, 4 * n) if use else (0, 0))),
    # field_kernel, per pixel: its fill index (row, column) 8 read, f0 8 written (kind 1: f0, f1 16); kind 0
    # ("intensity"): the mean grey value of the filled pixel's N observations (grey_of 7 and the sum 1 each, the
    # division 2), the observations 12 N per mask pixel (a pixel outside the mask reads its nearest mask pixel's: a
    # cache hit); kind 1: the filled pixel's normal 24 per mask pixel, clamp, 2 negations, 2 divisions 5.
    "dgmc_field": lambda n, kind: (((16, 8 * n + 3), (12 * n, 0)) if kind == 0 else ((24, 6), (24, 0))),
    # correlate_kernel (one separable pass of a Gaussian-derivative filter of nw taps), per pixel: its own value 8
    # read (the other taps' values: cache hits) and the result 8 written; per tap: the axis test 1, the index
    # (i + t - r: 2), scipy's reflect (%, < 0 and >= n tests and the fold: ~5), the weight's FMA 2: 10; the
    # radius 2.  Float64 FMA but mostly integer work: the float32 bound (as dgmc_start_search).
    "dgmc_correlate": lambda nw: ((16, 10 * nw + 2),),
    # curvature_kernel, per pixel: mask 1 read, GC and MC 16 written, the test 1; per mask pixel: the three
    # second derivatives 24 read (kind 1: four, 32), the eigenvalues (half trace 2, root 6 with its sqrt, k1 k2 2)
    # and GC, MC 3: 13 (kind 1: 3 more).  Float64.
    "dgmc_curvature": lambda kind: ((17, 1), ((24, 13) if kind == 0 else (32, 16))),
    # label_init_kernel, per pixel: region 1 read, label 4 written; the test and i W + j: 3.
    "dgmc_label_init": lambda: ((5, 3),),
    # label_min_kernel at the fixed point (no label changes: the last step of the labelling), per pixel: region 1
    # read and tested 1; per region pixel: its label 4 read (the neighbours' labels and region bytes: cache hits),
    # 9 offsets' neighbour tests (~3 each), per neighbour the offsets 2, bounds 4, region test 1, min 1 (8), the
    # pointer jump (division, remainder, min 3) and the change test 1: 95.
    "dgmc_label_min": lambda: ((4, 95), (1, 1)),
    # roots_kernel, per pixel: label 4 read, root flag 4 written; flat index 2, compare, select 2.
    "dgmc_roots": lambda: ((8, 4),),
    # label_number_kernel (in place), per pixel: label 4 read and 4 written, the test and the gather's index 2 (the
    # gathered numbers: one per region, cache hits).
    "dgmc_label_number": lambda: ((8, 2),),
    # boundary_kernel, per pixel: mask 1 read, boundary 4 written, the mask test 1; per mask pixel: region 1 read
    # and tested 1; per mask pixel off the region: 9 offsets' neighbour tests (3 each) and per neighbour the
    # offsets 2, bounds 4, label > 0 1, the best test 2 (9): 99, and its own label 4 B (read by its neighbours:
    # the labels of the region's ring are cache hits).
    "dgmc_boundary": lambda: ((5, 1), (1, 1), (4, 99)),
    # list_reset_kernel (one thread a list entry, H W K), per entry: key and source 8 written, the t == 0 test 1;
    # per pixel: its change mark 4 written.
    "dgmc_list_reset": lambda: ((8, 1), (4, 0)),
    # geodesic_slots_kernel, per pixel: region 1 read and tested 1, the slot code 4 written; per region pixel: its
    # label 4 read (the neighbours' labels, mask and region bytes: cache hits), 8 slots of offsets 2 (constant
    # loads) + adds 2, bounds 4, label compare 1, the code's shift and or 3 (10 each); per slot on another label
    # (borders called): its mask and region tests 2; per scanned offset of a borders call (a mask pixel off the
    # region: raster order until a pixel of the label is found) the neighbour test 3 and for a neighbour the adds
    # 2, bounds 4, label compare 1: 7 more (counted on the host from the labels).
    "dgmc_geodesic_slots": lambda: ((5, 1), (4, 80)),
    # per (candidate, sample): e evaluations of the sample's lit/unlit lights; outputs normal 12, albedo 12,
    # residual, iterations, flags 4 each.  Per sample (once for all candidates): strip 12 N, weights 4 N,
    # point, view, start 12 each, gmax and flags 4 each.
    "scorer_solve": lambda e, lit, n: ((36, e * (EVAL_LIT * lit + EVAL_UNLIT * (n - lit) + EVAL_FIXED)),
                                       (16 * n + 44, 0)),
    # The scorer's sample kernels (gpps.kernels.solve_batched; one thread a sample pixel).  gather_samples_kernel
    # (MaterialScorer.upload_from: the solver's frame, its valid flags and depth read), per sample: its row and
    # column 8 and depth 4 read, the strip's depth 4 written, the use_depth test 1; per image: the observation 12 and
    # valid flag 1 read, strip 12 and strip_valid 1 written, the loop's step and test 2 and the use_valid test 1.
    "scorer_gather_samples": lambda n: ((16 + 26 * n, 1 + 3 * n),),
    # prepare_samples_kernel (the material-free part of solve_kernel: least_squares' work without its residual),
    # per sample with fg of its n observations in the fit and fl in the least squares (as least_squares): bytes:
    # the strip 12 n and strip_valid n, row, column, depth 12 read, weights 4 n, point, view, start normal 36 and
    # gmax, flags, cond 12 written (the noise levels and the lights: cache hits).  FLOPs: per light grey_max 4 and the
    # weights 14, the in-fit tests of the Gram and least-squares loops ~8: 26; per light in the fit the Gram 19; per
    # light in the least squares 44 (least_squares'); per sample: the point and view direction ~22, cond_frobenius
    # ~114, the flags ~5, the solution ~191: ~332.
    "scorer_prepare_samples": lambda n, fg, fl: ((17 * n + 60, 332 + 26 * n + 19 * fg + 44 * fl),),
    # gather_start_kernel (MaterialScorer.set_start(frame=...): warm starts from a solve's normals), per sample: row
    # and column 8 and the frame's normal 12 read, the start 12 written; its length (3 mul, 2 add, sqrt: 6), the two
    # compares and the and 3; per sample whose normal is not unit: Woodham's start 12 read.
    "scorer_gather_start": lambda: ((32, 9), (12, 0)),
    # per masked pixel: e evaluations (all starts); images 12 N, valid N, weights written 4 N, depth 4;
    # every pixel: mask 1, outputs 40 (normal, albedo 12 each; residual, iterations, flags, cond 4 each).
    "pixel_solve": lambda e, lit, n: ((17 * n + 4, e * (EVAL_LIT * lit + EVAL_UNLIT * (n - lit) + EVAL_FIXED)),
                                      (41, 0)),
    # the warm solve (RON's rounds after the cold ones: warm_start, one start): pixel_solve's counts with the warm
    # solve's evaluations (its own and the neighbour pass's: the iterations output sums both), plus the start normal
    # 12 read per masked pixel (the normals buffer, then overwritten).  (The neighbour pass's ring search, Weiszfeld
    # medians and first-order fit of an under-determined pixel are not counted: as pixel_solve.)
    "pixel_solve_warm": lambda e, lit, n: ((17 * n + 16, e * (EVAL_LIT * lit + EVAL_UNLIT * (n - lit) + EVAL_FIXED)),
                                           (41, 0)),
    # merge_saved_kernel (PixelSolver.merge_saved after save: a warm solve of the selected pixels merged into the
    # saved cold one), per pixel: the selection byte 1 read and tested 1; per selected pixel: iterations, saved
    # iterations, residual, saved residual 16 read, the sum 4 written; the add and the compare 2; per selected pixel
    # with the lower residual: its flags 4 read, the and and test 2 (kept there where FLAG_FEW_OBSERVATIONS is
    # clear: nothing more); per restored pixel (not selected, or selected and not kept): the saved normal, albedo,
    # flags and cond 32 read, the five outputs (normal, albedo 12 each; residual, flags, cond 4 each) 36 written;
    # per pixel not selected: the saved iterations 4 read and written 4, the saved residual 4 read.
    "merge_saved": lambda: ((1, 1), (20, 2), (4, 2), (68, 0), (12, 0)),
    # solve_kernel of solver "none" (Woodham's least squares: gpps.kernels.solve_kernels' pixel_prelude, then
    # solve_common.store_least_squares; one thread a pixel, directional lights), per mask pixel with fg of its n
    # observations in the fit (weight != 0: kept or dark) and fl in the least squares (fg, or n where the lights'
    # Gram matrix is singular: FLAG_WOODHAM_FALLBACK): bytes: images 12 n, valid n, depth 4 read, weights 4 n, the
    # six outputs 40 written (normal, albedo 12 each; residual, iterations, flags, cond 4 each), mask 1 (the noise
    # levels and the lights: cache hits).  FLOPs: per light grey_max (grey 3, max 1), the weights (valid test,
    # grey 3, shadow and lit tests with their products ~8, the dark test, counts ~3: 14), the in-fit tests of the
    # Gram, least-squares and residual loops (~12): 30; per light in the fit the Gram's l l^T (9 mul + 9 add) and
    # the light's kind test: 19; per light in the least squares: y = I / E (3 tests, 3 divisions), l l^T 18,
    # b_c += y_c l (9 FMA: 18), kind tests 2: 44, and the residual (n.l 5, per channel E kd (n.l) 2, I - that 1,
    # r^2 summed 2: 15, ws 1, kind tests 2): 23; per pixel: the point and view direction ~22, cond_frobenius
    # (determinant 17, |A|_F 18, the singular test 6, inverse ~54, |A^-1|_F 19: ~114), the flags ~5, the solution
    # (b_g 6, determinant, norm and test 41, inverse 54, A^-1 b_g 15, normalise 15, the three channels' A^-1 b_c . n
    # 60: ~191), the albedo clamp 3, the residual's sqrt, division, test 3: ~340.  Per pixel outside the mask: the
    # mask 1 read, its outputs 40 and weights 4 n written; the test and n stores' loop n + 1.
    "least_squares": lambda n, fg, fl: ((17 * n + 45, 340 + 30 * n + 19 * fg + 67 * fl), (4 * n + 41, n + 1)),
    # per valid pixel and CG iteration (float64): loop 1 reads z, p_old, W_r, W_d, nb (4 int32) and writes q,
    # p_new (64 B; the 4 neighbours' z, p_old, W: cache); fused p = z + beta p_old for itself and 4
    # neighbours and A p (~25 FLOPs), p.q; loop 2 reads x, p_new, r, q, D^-1, writes x, r, z (64 B), 9 FLOPs
    # + 2 sums.
    "bini_cg_iteration": lambda: ((128, 36),),
    # per (candidate, sample): P compares of the sample against every value of its row over its segments (load
    # from cache, NaN key, two compares and an index compare, count: 5 ops each), one atomic add a segment;
    # bytes: its residual read 4 and its int32 count added 4 (the row's other values: cache hits).
    "search_trimmed_rank": lambda p: ((8, 5 * p),),
    # The device material search's other per-pass kernels (gpps.kernels.material_search; d searched parameters, K = 4
    # candidates, P samples, L = PARTIAL_LANES), float64.  search_points_kernel (one thread a candidate, a step pass),
    # per candidate: its material row 28 and point 8 d written; per parameter: the centroid (d adds, a division),
    # the worst vertex, the candidate's branch (<= 3 compares) and coefficients (~4), the clip 2, exp ~20, the
    # float32 cast 1, the field's branch <= 3: d + 34; the phase test 1.  Per launch (read once by all four): the
    # base row 28, the phase 4, the simplex 8 d (d + 1), bounds and fields 20 d.
    "search_points": lambda d: ((28 + 8 * d, 1 + d * (d + 34)), (32 + 8 * d * (d + 1) + 20 * d, 0)),
    # trimmed_contrib_kernel, per (candidate, sample): the rank count 4 read and cleared 4, the residual 4 read (its
    # sectors are fetched whether or not the value is kept), the contribution 8 written; the keep test 1, widening
    # and square 2 for a kept value (after the first timed launch every count is 0 < keep: all kept).
    "search_contrib": lambda: ((20, 3),),
    # trimmed_partial_kernel, per (candidate, sample): its contribution 8 read, the add and the strided loop's
    # index and test 3; per (candidate, lane): its partial 8 written, the start and lanes 2.
    "search_partial": lambda: ((8, 3), (8, 2)),
    # trimmed_energy_kernel (one thread a candidate): its L partials 8 L read, L adds and loop steps 2 L, the division
    # by keep 1 (and its widening), the energy 8 written.
    "search_energy": lambda lanes: ((8 * lanes + 8, 2 * lanes + 2),),
    # search_step_kernel (one thread), a step pass: cond 4, the state 16 read and written, up to two energies 16, the
    # simplex's values fsim 8 (d + 1) and vertices 8 d (d + 1) read and written (the stable re-sort, the accepted
    # point), the accepted candidate 8 d read; the decision ~16 (compares, budget tests, counters), the re-sort
    # (per vertex _after's NaN tests and compare ~4, a move of d values ~2 d), the size test (3 d^2 + 1).
    "search_step": lambda d: ((52 + 16 * (d + 1) + 16 * d * (d + 1) + 8 * d, 17 + d * (4 + 2 * d) + 3 * d * d),),
    # DGMC's solved front (gpps.kernels.front; one thread a ring pixel unless said).  front_source_kernel, per ring
    # pixel (all rings, one launch): its index, level 4, GC/MC 16 read, its source 4 written (the neighbours'
    # levels and curvatures: cache); index 2 and loads ~2, the widening loop's test every step (ws + 1); per
    # step scanned (entered still searching): 8 neighbour slots, each the offset decoded from r (~6), a, b (2) and
    # the gate's found < 0 (1): 9, and the tolerance's product 1: 73; Warp's `and` short-circuits (its generated
    # code tests each operand only after the previous one held), so a slot still searching adds 2 (compare, and)
    # per bound test evaluated, up to the first that fails (``bounds``, counted on the host); per slot gated in (in
    # bounds) the level compare 1; per solved neighbour reached the first-candidate test and the curvature flag 2
    # and the Gaussian curvature's half of the test 5 (sub, 2 abs, mul, compare), and where that half holds the
    # mean curvature's 5 and the and 1 (``second``).  The tests are float64, the bulk of the ops integer: the
    # float32 bound (as dgmc_start_search).
    "front_source": lambda steps, bounds, gated, checks, second, ws: (
        (28, 4 + (ws + 1) + 73 * steps + 2 * bounds + gated + 7 * checks + 6 * second),),
    # scatter_mask_kernel (PixelSolver.select_pixels), per ring pixel: its index 4 read, the mask byte written;
    # start + t, p // W, p % W.
    "front_scatter_mask": lambda: ((5, 3),),
    # front_start_kernel, per ring pixel: index and source 8 read, the start normal 12 written; index 1, two
    # divisions and two remainders 4; per distinct source of the ring: its current normal 12 read.
    "front_start": lambda: ((20, 5), (12, 0)),
    # front_merge_kernel (keep_better), per ring pixel: index 4, the solve's evaluations 4 read and written 4,
    # the two residuals and the flags 12 read; index 3, compare, and, flag test, not ~5; per pixel where the
    # solve wins: its normal and albedo 24 read, the current normal, albedo, residual, flags and won 33 written.
    "front_merge": lambda: ((24, 8), (57, 0)),
    # front_write_back_kernel, per pixel (dim H x W): the merged normal, albedo, residual, flags and both
    # evaluation counts 40 read, the solver's five outputs 36 written; one add.
    "front_write_back": lambda: ((76, 1),),
    # front_source_normals_kernel, per ring pixel (all rings): its source 4 read, the normal 12 written; the
    # test, division and remainder 3; per distinct source: its merged normal 12 read.
    "front_source_normals": lambda: ((16, 3), (12, 0)),
    # curvature_in_kernel (DeviceFront.upload: DGMC's device curvatures rounded to float32 and back, one launch a
    # map; dim H x W), per pixel and map: the value 8 read, 8 written, the two casts 2.  Float64.
    "front_curvature_in": lambda: ((16, 2),),
    # round_sums_kernel (RON's device rounds; one thread a run of ROUND_CHUNK pixels of a row), per mask pixel:
    # residual 4, normal 12, previous normal 12 read; float64: r^2 and its sum 3, 6 widenings, both |v|^2 10,
    # their tests 3, the cross product 9, its length 6 (sqrt 1), a.b 5, atan2 ~40 (a division and a polynomial
    # of degree ~20 in Horner form), the two sums 2: ~84.  Per pixel: the mask byte, its test and the loop 3.
    # (Each thread's three float64 atomic adds, all to one address, are not traffic.)
    "rounds_sums": lambda: ((28, 84), (1, 3)),
    # one fused PCG iteration of the rounds' multigrid integrator (gpps.kernels.poisson.pcg_iteration, float32
    # fields, float64 sums), counted per Taichi task (a top-level loop: tasks meet at a global barrier, so a
    # value written by one task and read by the next counts in both, as bini_cg_iteration), per grid point of
    # each level, active (dg > 0: in the mask) or not; neighbours' values and weights are cache hits.
    # Level 0's CG loops, active: q = A p (dg, p, wx, wy 16 read, q 4 written; the 4-neighbour sum ~13 with its
    # bounds tests, d p - s, p.q widened and summed: 20); the update (x, p, r, q read, x, r, f, e written 32 B;
    # 2 axpys, r^2 widened and summed, alpha cast: 8); r.e (8 B, 4); p = e + beta p (12 B, 2): 72 B, 34 FLOPs;
    # inactive: A p reads dg and p and writes q (12 B, 5), the other three loops as active: 64 B, 19 FLOPs.
    # V-cycle, per point of each level but the coarsest (down, then up), active: 4 damped Jacobi sweeps
    # (smooth_pairs 1: 2 before and 2 after; dg, e, f, wx, wy read, t or e written 24 B; test, 1 - omega
    # product, f + neighbour sum 14, / d, omega *, + : 18), the residual (24 B, 17), the injection (dg, e 8
    # read, the coarse e 1 a point, e written 4: 13 B; test, add, 2 index halvings: 4): 133 B, 93 FLOPs;
    # inactive (dg read and tested, the store; x * 0 taken as folded by fast math, no read): 4 sweeps and the
    # residual 8 B, 1 each, injection 4 B, 1: 44 B, 6 FLOPs.  Per point of each coarser level (restriction): 4 fine residuals
    # 16 read, f and e 8 written, 3 adds and 3 bounds tests.  The coarsest level's exact solve (one serial
    # task): nc^2 entries of pinv 4 B and a multiply-add, the gathered f, cidx and e 16 B per active cell.
    "rounds_pcg_iteration": lambda nc: (((72, 34), (64, 19)), ((133, 93), (44, 6)), (24, 6),
                                        (4 * nc * nc + 16 * nc, 2 * nc * nc)),
    # The rest of the rounds' integration (DeviceRounds.integrate -> gpps.pipeline.integration_rounds.DeviceSystem,
    # its Taichi kernels gpps.kernels.poisson_weighted and the integrator's gpps.kernels.poisson; float64 assembly
    # fields gj, gi, cj, ci, float32 multigrid fields, i32 mask and labels; Taichi does not short-circuit `and`:
    # every operand is read).  Counted per Taichi task as rounds_pcg_iteration, per grid point.
    # assemble_pixels, per pixel: mask 4 read, gj, gi, cj, ci 32 written, the test 1; per mask pixel: its normal 12
    # read (float32), 3 widenings, |n| 6, the validity tests 5, normalise 3, the camera-facing test 11, m's clamp 1,
    # the steps 6, the factors -f m 2 and their squares 2 ("normal" weighting), the two statistics' adds 2: 41.
    # Float64 (perspective, weighted: RON's case).
    "rounds_assemble_pixels": lambda: ((36, 1), (12, 41)),
    # assemble_edges, per pixel: gj, gi, cj, ci 32 read (the neighbours': cache hits), wx, wy, dg, b 16 written; its
    # (up to) 4 edges each computed (both pixels of an edge compute it): shares 4 mul, the validity tests and a + b
    # 6: 10, and per valid edge the flux (2 mul, add, division, product: 5 more); the bounds tests 4, d and rhs
    # sums 8, 4 casts: 56 + 5 a valid edge end.  Float64.
    "rounds_assemble_edges": lambda: ((48, 56), (0, 5)),
    # coarsen (one call a level; two tasks), per coarse point: task 1 reads the fine weights leaving its block (two
    # j-edges of its right column, two i-edges of its bottom row: 16 B; the others are never read) and writes its wx,
    # wy 8: its tests and indices ~20, 4 widenings and adds, the alpha products and casts 4: ~30; task 2 reads its
    # wx, wy 8 (the neighbours': cache hits) and writes dg 4, 3 adds and 2 tests 5.  Float64 products, mostly
    # integer work: the float32 bound.
    "rounds_coarsen": lambda: ((36, 35),),
    # gather_level, per coarsest cell: wx, wy 8 read, 2 float64 16 written; 2 widenings, the offset index 1.
    "rounds_gather_level": lambda: ((24, 3),),
    # residual_norm (|b|^2 at the CG's start: r = b - A x, sc[RR] = |r|^2), per level-0 point, active (dg > 0): dg,
    # x, b, wx, wy 20 read, r 4 written; the 4-neighbour sum with its bounds tests ~13, b - d x and + 3, the test,
    # widening, square and sum 4: 20; inactive: dg 4 read, r 4 written, the test, square and sum 3.
    "rounds_residual_norm": lambda: ((24, 20), (8, 3)),
    # pcg_start (fused: cg_start, the first V-cycle, cg_first_direction), per level-0 point: cg_start active:
    # dg, x, b, wx, wy 20 read, r, f, e 12 written, 20 FLOPs (as residual_norm); inactive: dg 4 read, r, f, e 12
    # written, 3; cg_first_direction at every point: r, e 8 read, p 4 written, r e widened and summed 4; the V-cycle
    # as rounds_pcg_iteration's.
    "rounds_pcg_start": lambda: (((32, 20), (16, 3)), (12, 4)),
    # component_sums, per pixel (csum, ccnt, cmax, cmin are dense H W fields indexed by a component's root pixel):
    # the clear of the four 32 written, cj 8 and lab 4 read, the tests 3, the span task's ccnt 8 read and test 1;
    # per valid pixel: z 4 read, widening, 2 adds, atomic max and min 5 (the atomics to one component's entries: cache
    # hits, not traffic; on CUDA they contend).  Float64.
    "rounds_component_sums": lambda: ((52, 4), (4, 5)),
    # depth_exp (perspective), per pixel: cden's clear 8 written, cj 8, lab 4 read, the tests 3; per valid pixel: z
    # 4 read, widening and - max z 2, exp ~20, the add 1: 23.  Float64.
    "rounds_depth_exp": lambda: ((20, 3), (4, 23)),
    # depth_write, per pixel: cj 8 and lab 4 read, the tests 3; per valid pixel: z 4 read, the depth 4 written
    # (float32); u (widening, mean z, sub) 3, + ref 1, the perspective form (exp(z - max z) ~21, the mean's and
    # ref's divisions, the product 3), the cast 1, the fill sums 3: 32.  Float64.
    "rounds_depth_write": lambda: ((12, 3), (8, 32)),
    # depth_fill, per pixel: mask 4 read and tested 1; outside the mask: the depth 4 written; per mask pixel: cj
    # 8, lab 4 and the depth 4 read, the three tests, and, not 5 (a dropped pixel's fill store not counted).
    "rounds_depth_fill": lambda: ((4, 1), (4, 0), (16, 5)),
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


def _taichi_row(ctx, name, pattern, fn, by, fl, *, f64=False, extra=None, inner=10):
    """A Taichi call's row: timed with ``ti.sync`` (or registered for the profiler, its tasks matched by
    ``pattern``), with its counts ``by`` and ``fl``."""
    t = _time_or_register(ctx, name, pattern, fn, inner=inner, taichi=True, per_launch=None)
    if t is not None:
        row(ctx, name, t, by, fl, f64=f64, extra=extra)


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
    _dgmc_other_rows(ctx, st, info, m, region)


def _slots_work(mask, region, labels, conn):
    """Per region pixel: the FLOPs of :func:`gpps.kernels.dgmc_geodesic.geodesic_slots_kernel`'s ``borders`` calls
    (COUNTS_CHAIN["dgmc_geodesic_slots"]), replayed on the host from the labels: 2 a slot on another label, and
    for a mask pixel off the region there the scan of its 3 x 3 offsets in raster order until a neighbour of the
    label (3 an offset, 7 more a neighbour offset)."""
    h, w = labels.shape
    ri, rj = np.nonzero(region)
    lab = labels[ri, rj][:, None]
    oi = np.array([-1, -1, -1, 0, 0, 1, 1, 1])
    oj = np.array([-1, 0, 1, -1, 1, -1, 0, 1])
    a, b = ri[:, None] + oi, rj[:, None] + oj
    inb = (a >= 0) & (a < h) & (b >= 0) & (b < w)
    ac, bc = np.clip(a, 0, h - 1), np.clip(b, 0, w - 1)
    other = inb & (labels[ac, bc] != lab)
    scan = other & mask[ac, bc] & ~region[ac, bc]
    di, dj = np.repeat([-1, 0, 1], 3), np.tile([-1, 0, 1], 3)
    nb = ~((di == 0) & (dj == 0)) & ((conn == 8) | (di == 0) | (dj == 0))
    c, d = ac[..., None] + di, bc[..., None] + dj
    inb2 = (c >= 0) & (c < h) & (d >= 0) & (d < w)
    hit = nb & inb2 & (labels[np.clip(c, 0, h - 1), np.clip(d, 0, w - 1)] == lab[..., None])
    visited = np.where(hit.any(-1), hit.argmax(-1) + 1, 9)  # offsets scanned (the found one included)
    nbv = np.cumsum(nb)[visited - 1]  # neighbour offsets among them
    return (2 * other + scan * (3 * visited + 7 * nbv)).sum(1).astype(np.float64)


def _dgmc_other_rows(ctx, st, info, m, region):
    """The rest of :meth:`DeviceDGMC.step`'s kernels, one launch each as the step launches them (outputs into scratch
    arrays where a launch would change what another row reads): the reference albedo's sample and median, the
    saturation pass, the curvatures' field, one correlate pass along each axis and the curvatures, the regions'
    labelling (init, one min-label step at the fixed point, roots, numbering, boundary), a list reset and the
    geodesic slots.  (Warp's radix sort of the median and the labels' scan are library launches: no rows.)"""
    from gpps.kernels import dgmc as dk
    from gpps.kernels import dgmc_geodesic as dg

    wp = _wp()
    dev = ctx.device
    n, h, w = st.shape
    cfg = st.config
    hw = h * w
    mp = int(m.sum())
    nr = int(region.sum())
    conn = int(cfg.connectivity)
    light = [st.light_kind, st.lvec, st.laxis, st.lmu, st.lint, st.points]
    f64, i32, u8 = wp.float64, wp.int32, wp.uint8
    keys_s, vals_s = wp.empty(2 * hw, dtype=f64, device=dev), wp.empty(2 * hw, dtype=i32, device=dev)
    rho_s = wp.zeros(1, dtype=f64, device=dev)
    sat_s, reg_s = wp.empty((n, h, w), dtype=u8, device=dev), wp.empty((h, w), dtype=u8, device=dev)
    f_s = [wp.empty((h, w), dtype=f64, device=dev) for _ in range(4)]
    lab_s, lab2_s = wp.empty((h, w), dtype=i32, device=dev), wp.empty((h, w), dtype=i32, device=dev)
    roots_s, bnd_s = wp.empty(hw, dtype=i32, device=dev), wp.empty((h, w), dtype=i32, device=dev)
    k = int(cfg.k_nearest)
    lk_s, ls_s = wp.empty((h, w, k), dtype=i32, device=dev), wp.empty((h, w, k), dtype=i32, device=dev)
    ch_s, slots_s = wp.empty((h, w), dtype=i32, device=dev), wp.empty((h, w), dtype=i32, device=dev)
    count_s = wp.zeros(1, dtype=i32, device=dev)
    ctx.keep.append((keys_s, vals_s, rho_s, sat_s, reg_s, f_s, lab_s, lab2_s, roots_s, bnd_s, lk_s, ls_s, ch_s,
                     slots_s, count_s))

    def launch(kernel, dim, inputs):
        return lambda: wp.launch(kernel, dim=dim, inputs=inputs, device=dev)

    def one(name, kernel, dim, inputs, by=None, fl=None, f64=False, extra=None, inner=10):
        t = _time_or_register(ctx, name, f"^{kernel.key}_", launch(kernel, dim, inputs), inner=inner)
        if t is not None:
            row(ctx, name, t, by, fl, f64=f64, extra={**info, **(extra or {})})
        return t

    # the upload's conversion of a solve's float32 normals (RON uploads its solver's normals buffer): the stage's
    # float64 normals as float32, into scratch
    src_s = wp.array(st.normals.numpy().astype(np.float32), dtype=wp.vec3, device=dev)
    nrm_s = wp.empty((h, w), dtype=wp.vec3d, device=dev)
    ctx.keep.append((src_s, nrm_s))
    (pb, pf), (qb, qf) = COUNTS_CHAIN["dgmc_start_normals"]()
    one("dgmc_start_normals", dk.start_normals_kernel, (h, w), [src_s, st.mask, nrm_s], pb * hw + qb * mp,
        pf * hw + qf * mp, f64=True, extra={"summary": f"{h}x{w} px, {mp} in the mask",
                                             "note": "DeviceDGMC.upload of a solve's float32 normals (into scratch)"})
    if cfg.rule == "lambertian":
        (pb, pf), (ab, af) = COUNTS_CHAIN["dgmc_albedo_sample"](n)
        one("dgmc_albedo_sample", dk.albedo_sample_kernel, (h, w),
            [st.images, st.channels, st.mask, *light, keys_s, vals_s], pb * mp + ab * hw, pf * mp + af * hw,
            f64=True, extra={"summary": f"{mp} px x {n} observations", "note": "the reference albedo's sample"})
        ((b1, f1),) = COUNTS_CHAIN["dgmc_median"]()
        one("dgmc_median", dk.median_kernel, 1, [st.sort_keys, st.count, rho_s, 0], b1, f1, f64=True,
            extra={"summary": "one thread", "note": "one thread on the sorted keys: the launch's fixed cost is all "
                                                    "of it (the radix sort before it: Warp's, no row)"})
    sat = cfg.saturation
    use = sat is not None
    (sb, sf), (ub, uf) = COUNTS_CHAIN["dgmc_saturation"](n, use)
    one("dgmc_saturation", dk.saturation_kernel, (h, w),
        [st.images, st.channels, st.mask, 0.0 if sat is None else float(sat), int(use), st.flags, sat_s, reg_s],
        sb * hw + ub * mp, sf * hw + uf * mp, extra={"saturation_test": use, "summary": f"{h}x{w} px x {n} flags",
               "note": "the saturated observations join the flags (none without DGMCConfig.saturation: the "
                       "images not read), the region byte"})
    kind = 0 if cfg.curvature_field == "intensity" else 1
    (fb, ff), (gb, _) = COUNTS_CHAIN["dgmc_field"](n, kind)
    one("dgmc_field", dk.field_kernel, (h, w), [st.images, st.channels, st.normals, kind, st.fill, f_s[0], f_s[1]],
        fb * hw + gb * mp, ff * hw, f64=True, extra={"curvature_field": cfg.curvature_field,
                                                    "summary": f"{h}x{w} px, {mp} in the mask",
                                                    "note": "the curvatures' field, filled outside the mask"})
    wt = st.weights[2 if kind == 0 else 1]
    nw = int(wt.shape[0])
    ((cb, cf),) = COUNTS_CHAIN["dgmc_correlate"](nw)
    for axis, src, dst in ((0, st.f[0], f_s[2]), (1, f_s[2], f_s[3])):
        one(f"dgmc_correlate_{'ij'[axis]}", dk.correlate_kernel, (h, w), [src, wt, axis, dst], cb * hw, cf * hw,
            extra={"taps": nw, "axis": axis, "summary": f"{h}x{w} px, {nw} taps along {'ij'[axis]}",
                   "note": f"one separable pass ({2 * (3 if kind == 0 else 4)} a step, along both axes)"})
    (pb, pf), (qb, qf) = COUNTS_CHAIN["dgmc_curvature"](kind)
    d = st.deriv
    one("dgmc_curvature", dk.curvature_kernel, (h, w), [st.mask, kind, d[0], d[1], d[2], d[3], f_s[0], f_s[1]],
        pb * hw + qb * mp, pf * hw + qf * mp, f64=True, extra={"summary": f"{h}x{w} px, {mp} in the mask",
                                     "note": "GC and MC from the filtered derivatives"})

    # the regions: the labelling's kernels on scratch labels (the stage's numbered labels stay as they are)
    ((ib, i_f),) = COUNTS_CHAIN["dgmc_label_init"]()
    one("dgmc_label_init", dg.label_init_kernel, (h, w), [st.region, lab_s], ib * hw, i_f * hw,
        extra={"summary": f"{h}x{w} px", "note": "the labels' start (into scratch labels)"})
    wp.launch(dg.label_init_kernel, dim=(h, w), inputs=[st.region, lab_s], device=dev)
    for _ in range(hw + 1):  # to the fixed point (as DeviceDGMC._regions)
        count_s.zero_()
        wp.launch(dg.label_min_kernel, dim=(h, w), inputs=[st.region, conn, lab_s, count_s], device=dev)
        if int(count_s.numpy()[0]) == 0:
            break
    (rb, rf), (pb, pf) = COUNTS_CHAIN["dgmc_label_min"]()
    one("dgmc_label_min", dg.label_min_kernel, (h, w), [st.region, conn, lab_s, count_s], rb * nr + pb * hw,
        rf * nr + pf * hw, extra={"region_pixels": nr, "summary": f"{nr} region px",
                                  "note": "one min-label step at the fixed point (nothing changes: the last of the "
                                          "labelling's steps; the others write their changed labels)"})
    ((ob, of),) = COUNTS_CHAIN["dgmc_roots"]()
    one("dgmc_roots", dg.roots_kernel, (h, w), [lab_s, roots_s], ob * hw, of * hw,
        extra={"summary": f"{h}x{w} px", "note": "the components' first pixels (on the fixed-point labels)"})
    wp.copy(lab2_s, lab_s)
    ((nb_, nf),) = COUNTS_CHAIN["dgmc_label_number"]()
    one("dgmc_label_number", dg.label_number_kernel, (h, w), [st.numbers, lab2_s], nb_ * hw, nf * hw,
        extra={"summary": f"{h}x{w} px", "note": "in place on a scratch copy of the min labels (the launches after "
                                                 "the first renumber numbers: the same per-pixel work)"})
    mask_h = st.mask.numpy().astype(bool)
    cand = mask_h & ~region
    (ab, af), (mb, mf), (xb, xf) = COUNTS_CHAIN["dgmc_boundary"]()
    one("dgmc_boundary", dg.boundary_kernel, (h, w), [st.mask, st.region, st.labels, conn, bnd_s],
        ab * hw + mb * mp + xb * int(cand.sum()), af * hw + mf * mp + xf * int(cand.sum()),
        extra={"summary": f"{int(cand.sum())} mask px off the region",
               "note": "the outer boundary labelled with the smallest adjacent region (into scratch)"})

    # the geodesic phase's set-up: a list reset (two a step) and the slot kinds
    (eb, ef), (cb2, _) = COUNTS_CHAIN["dgmc_list_reset"]()
    one("dgmc_list_reset", dg.list_reset_kernel, (h, w, k), [lk_s, ls_s, ch_s], eb * hw * k + cb2 * hw,
        ef * hw * k, extra={"k_nearest": k, "summary": f"{h}x{w} x {k} entries",
                            "note": "one of the step's two list resets"})
    (sb, sf), (rb, rf) = COUNTS_CHAIN["dgmc_geodesic_slots"]()
    extra_fl = _slots_work(mask_h, region, st.labels.numpy(), conn)
    one("dgmc_geodesic_slots", dg.geodesic_slots_kernel, (h, w), [st.mask, st.region, st.labels, conn, slots_s],
        sb * hw + rb * nr, sf * hw + rf * nr + float(extra_fl.sum()),
        extra={"region_pixels": nr, "mean_border_flops": float(extra_fl.mean()) if nr else 0.0,
               "summary": f"{nr} region px",
               "note": "the 8 slots' kinds of every region pixel (borders' scans counted on the host)"})


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
    if scorer.split_starts:
        # RON's cold candidate solves on CUDA: the starts-parallel build (one thread a start, then the pick)
        scorer.set_candidates(cands)
        ts = _time_or_register(ctx, f"scorer_starts_{n_images}img", "solve_(starts|finish)_kernel", scorer.launch,
                               inner=3, per_launch=2)
        if ts is not None:
            ev2 = scorer.iterations.numpy()[:n_cand, :p].astype(np.float64)
            lit = lit_count(sc.normals[scorer.rows_host, scorer.cols_host], lights.directions)
            (cb2, cf2), (sb2, _) = COUNTS_CHAIN["scorer_solve"](ev2, lit[None, :], n_images)
            row(ctx, f"scorer_starts_{n_images}img", ts, cb2 * ev2.size + sb2 * p, float(np.sum(cf2)),
                extra={"images": n_images, "candidates": n_cand, "samples": p, "mean_evaluations": float(ev2.mean()),
                       "mean_lit": float(lit.mean()), "summary": f"K={n_cand} P={p}, {ev2.mean():.1f} evaluations/item",
                       "note": "MaterialScorer.launch, starts-parallel: solve_starts_kernel (one thread a start) + "
                               "solve_finish_kernel (the pick); counts as the one-thread build's"})
    ctx.keep.append(scorer)


def scorer_sample_rows(ctx, n_images, samples, n_cand):
    """The scorer's sample kernels as RON launches them, one launch each: the gather of the sample from a
    :class:`PixelSolver`'s frame (:meth:`MaterialScorer.upload_from`: ``gather_samples_kernel``), the sample's
    material-free terms (``prepare_samples_kernel``, :meth:`MaterialScorer.upload` too) and the warm starts from
    the solver's normals (:meth:`MaterialScorer.set_start` with ``frame``: ``gather_start_kernel``).  The solver is
    RON's first step (least squares: its normals stand in for a round's; the gather tests only that they are
    unit)."""
    from gpps.kernels import solve_batched as sb
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    wp = _wp()
    dev = ctx.device
    t0 = time.perf_counter()
    sc, mat, lights, img, scorer, p = _sample_scorer(ctx, n_images, samples, n_cand)
    ps = PixelSolver(img.shape[:3], sc.camera, lights, mat, replace(SolverConfig(), solver="none", smoothness=0.0),
                     device=dev)
    ctx.keep.extend([scorer, ps])
    ps.upload(img, sc.mask)
    ps.step()
    sample = np.zeros(sc.mask.shape, bool)
    sample[scorer.rows_host, scorer.cols_host] = True
    scorer.upload_from(ps, sample)
    scorer.set_start(frame=ps.normals)
    _sync(ctx)
    ctx.log(f"[chain {ctx.size}] scorer sample {n_images} images, P={p}: solve, gather and start "
            f"{time.perf_counter() - t0:.1f}s")
    info = {"images": n_images, "samples": p}

    def gather():  # (upload_from's: the solver's valid flags and depth read)
        wp.launch(sb.gather_samples_kernel, dim=p,
                  inputs=[ps.images, ps.valid, ps.depth, scorer.rows, scorer.cols, 1, 1],
                  outputs=[scorer.strip, scorer.strip_valid, scorer.sample_depth], device=dev)

    name = f"scorer_gather_samples_{n_images}img"
    t = _time_or_register(ctx, name, "^gather_samples_kernel_", gather, inner=20)
    if t is not None:
        ((gb, gf),) = COUNTS_CHAIN["scorer_gather_samples"](n_images)
        row(ctx, name, t, gb * p, gf * p,
            extra={**info, "summary": f"P={p} x {n_images} observations",
                   "note": "MaterialScorer.upload_from's gather from the solver's frame (valid and depth read)"})

    # (recorded once: a plain CPU launch re-packs its struct arguments every time)
    cmd = wp.launch(sb.prepare_samples_kernel, dim=p,
                    inputs=[scorer.strip, scorer.strip_valid, scorer.rows, scorer.cols, scorer.sample_depth,
                            scorer.noise, scorer.cam, scorer.lp, scorer.prm],
                    outputs=[scorer.base_weights, scorer.points, scorer.views, scorer.ninit, scorer.gmax,
                             scorer.flags, scorer.cond], device=dev, record_cmd=True)
    name = f"scorer_prepare_samples_{n_images}img"
    t = _time_or_register(ctx, name, "^prepare_samples_kernel_", cmd.launch, inner=20)
    if t is not None:
        from gpps.names import ASIDE_WEIGHT, FLAG_WOODHAM_FALLBACK

        wt = scorer.base_weights.numpy()[:, 0, :p]  # (N, P)
        fg = ((wt != 0.0) & (wt != ASIDE_WEIGHT)).sum(0).astype(np.float64)
        fallback = (scorer.flags.numpy()[:p] & int(FLAG_WOODHAM_FALLBACK)) != 0
        fl = np.where(fallback, float(n_images), fg)
        ((qb, qf),) = COUNTS_CHAIN["scorer_prepare_samples"](n_images, fg, fl)
        row(ctx, name, t, qb * p, float(np.sum(qf)),
            extra={**info, "mean_in_fit": float(fg.mean()), "woodham_fallback": int(fallback.sum()),
                   "summary": f"P={p}, {fg.mean():.1f}/{n_images} observations in the fit",
                   "note": "MaterialScorer's prepare (upload, upload_from): weights, flags, the lights' condition "
                           "and Woodham's start of every sample pixel"})

    def start():
        wp.launch(sb.gather_start_kernel, dim=p, inputs=[ps.normals, scorer.rows, scorer.cols, scorer.ninit],
                  outputs=[scorer.nwarm], device=dev)

    name = f"scorer_gather_start_{n_images}img"
    t = _time_or_register(ctx, name, "^gather_start_kernel_", start, inner=20)
    if t is not None:
        ln = np.linalg.norm(ps.normals.numpy()[scorer.rows_host, scorer.cols_host].astype(np.float64), axis=1)
        off = int(np.sum(~((ln > 0.999) & (ln < 1.001))))
        (sb_, sf), (ob, _) = COUNTS_CHAIN["scorer_gather_start"]()
        row(ctx, name, t, sb_ * p + ob * off, sf * p,
            extra={**info, "not_unit": off, "summary": f"P={p}, {off} not unit",
                   "note": "MaterialScorer.set_start(frame=...): the sample's warm starts from the solver's normals"})


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
    # the lights-parallel solve, then the neighbour pass: underdetermined_kernel, or where the config's cold solve
    # would run starts-parallel (CUDA) its three starts-parallel launches (as pixel_solve_rows)
    split = ps._uses_split()
    pattern = "(solve_kernel_lanes|underdetermined_kernel|under_(prelude|starts|finish)_kernel)"
    t = _time_or_register(ctx, name, pattern, ps.step, inner=2, per_launch=1 + (3 if split else 1))
    if t is not None:
        out = ps.fetch(("normals", "iterations"))
        ev = out["iterations"][ring].astype(np.float64)
        lit = lit_count(sc.normals[ring], lights.directions)
        (pb, pf), (ab, _) = COUNTS_CHAIN["pixel_solve"](ev, lit, n_images)
        row(ctx, name, t, pb * ev.size + ab * h * w, float(np.sum(pf)),
            extra={"images": n_images, "mask_pixels": int(ev.size), "lanes": 32,
                   "mean_evaluations": float(ev.mean()), "mean_lit": float(lit.mean()),
                   "summary": f"{int(ev.size)} px x 32 lanes, {ev.mean():.1f} evaluations/px",
                   "note": "solve_kernel (lights-parallel) + "
                           + ("under_prelude/starts/finish_kernel" if split else "underdetermined_kernel")
                           + " (the neighbour pass) on a ring subset"})
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


def pixel_solve_warm_rows(ctx, n_images):
    """RON's warm solve (its rounds after the cold ones, ``RON._solve(..., cold=False)``): the default
    :class:`SolverConfig` with ``warm_start=True, starts=1`` (the neighbour pass kept) from the solver's own cold
    normals, :meth:`PixelSolver.step` over the whole image."""
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    t0 = time.perf_counter()
    sc, mat, lights, img = ball_scene(ctx.size, n_images, ctx.device)
    m = sc.mask
    h, w = m.shape
    ps = PixelSolver(img.shape[:3], sc.camera, lights, mat, SolverConfig(), device=ctx.device)
    ctx.keep.append(ps)
    ps.upload(img, m)
    ps.step()  # the cold rounds' solve
    cold = ps.fetch(("normals", "iterations"))
    cfg = replace(SolverConfig(), warm_start=True, starts=1)  # RON's warm rounds
    ps.set_config(cfg)
    ps.set_start(cold["normals"])  # (RON: the previous round's normals)
    ps.step()
    _sync(ctx)
    ctx.log(f"[chain {ctx.size}] warm pixel solve {n_images} images: cold and first warm solve "
            f"{time.perf_counter() - t0:.1f}s")
    name = f"pixel_solve_warm_{n_images}img"
    # the kernels ps.step launches with a warm config: the solve (never starts-parallel: one start; its
    # lights-parallel form where config.parallel picks it), then the neighbour pass, underdetermined_kernel
    # (starts-parallel only where the config's whole-image solve is: never warm)
    lanes, split = ps._uses_lanes(), ps._uses_split()
    if split:
        raise RuntimeError(f"{name}: a warm config runs starts-parallel ({cfg})")
    solve = ps._lanes_kernel if lanes else ps._solve_kernel
    under = cfg.neighbour_radius > 0 and ps._underdetermined_kernel is not None
    keys = [solve.key] + ([ps._underdetermined_kernel.key] if under else [])
    t = _time_or_register(ctx, name, f"^({'|'.join(keys)})_", ps.step, inner=2, per_launch=len(keys))
    if t is not None:
        from gpps.host.metrics import normal_errors
        from gpps.names import FLAG_FEW_OBSERVATIONS

        out = ps.fetch(("normals", "iterations", "flags"))
        ev = out["iterations"][m].astype(np.float64)
        few = (out["flags"][m] & int(FLAG_FEW_OBSERVATIONS)) != 0
        lit = lit_count(sc.normals[m], lights.directions)
        (pb, pf), (ab, _) = COUNTS_CHAIN["pixel_solve_warm"](ev, lit, n_images)
        row(ctx, name, t, pb * ev.size + ab * h * w, float(np.sum(pf)),
            extra={"images": n_images, "mask_pixels": int(ev.size), "mean_evaluations": float(ev.mean()),
                   "cold_mean_evaluations": float(cold["iterations"][m].mean()),
                   "neighbour_pass_pixels": int(few.sum()),
                   "neighbour_pass_mean_evaluations": float(ev[few].mean()) if few.any() else 0.0,
                   "mean_lit": float(lit.mean()), "maen_deg": normal_errors(out["normals"], sc.normals, m)["mean"],
                   "summary": f"{ev.mean():.1f} evaluations/px, {int(few.sum())} px in the neighbour pass",
                   "note": " + ".join(["solve_kernel_lanes" if lanes else "solve_kernel"]
                                      + (["underdetermined_kernel (the neighbour pass)"] if under else []))
                           + ", default SolverConfig with warm_start=True, starts=1 (RON's warm rounds), from the "
                             "solver's own cold normals: at the solution the LM stops after a few evaluations, as "
                             "RON's warm rounds do from the previous round's normals (representative)"})


def merge_saved_rows(ctx, n_images=3):
    """:meth:`PixelSolver.merge_saved` as RON's cold rounds with start normals run it (``RON._solve`` with
    ``init``): the cold solve of the mask, :meth:`PixelSolver.save`, the warm solve of the mask (one start, no
    neighbour pass) from the cold normals, then the merge: one ``merge_saved_kernel`` launch over the image (3 images:
    RON's 256^2 x 3 case; the kernel reads no observations)."""
    from gpps.names import FLAG_FEW_OBSERVATIONS
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    t0 = time.perf_counter()
    sc, mat, lights, img = ball_scene(ctx.size, n_images, ctx.device)
    m = sc.mask
    h, w = m.shape
    cfg = SolverConfig()
    ps = PixelSolver(img.shape[:3], sc.camera, lights, mat, cfg, device=ctx.device)
    ctx.keep.append(ps)
    ps.upload(img, m)
    ps.step()
    start = ps.fetch(("normals",))["normals"]
    ps.save()
    ps.set_config(replace(cfg, warm_start=True, starts=1, neighbour_radius=0, smoothness=0.0))
    ps.set_start(start)  # (RON: the previous round's normals)
    ps.step()
    ps.merge_saved()
    _sync(ctx)
    ctx.log(f"[chain {ctx.size}] merge {n_images} images: cold and warm solves, first merge "
            f"{time.perf_counter() - t0:.1f}s")
    t = _time_or_register(ctx, "merge_saved", "^merge_saved_kernel_", ps.merge_saved, inner=20)
    if t is not None:
        sel = ps.mask.numpy().astype(bool)
        sv = ps._saved
        lower = sel & (ps.residual.numpy() < sv["residual"].numpy())
        kept = lower & ((ps.flags.numpy() & int(FLAG_FEW_OBSERVATIONS)) == 0)
        restored = ~kept
        n_sel, n_lower, n_kept, n_rest = (int(x.sum()) for x in (sel, lower, kept, restored))
        (xb, xf), (sb, sf), (lb, lf), (rb, _), (ub, _) = COUNTS_CHAIN["merge_saved"]()
        hw = h * w
        row(ctx, "merge_saved", t, xb * hw + sb * n_sel + lb * n_lower + rb * n_rest + ub * (hw - n_sel),
            xf * hw + sf * n_sel + lf * n_lower,
            extra={"images": n_images, "selected_pixels": n_sel, "kept_pixels": n_kept, "restored_pixels": n_rest,
                   "summary": f"{h}x{w} px, {n_kept}/{n_sel} selected kept",
                   "note": "merge_saved_kernel, one launch over the image after a warm solve of the mask from the "
                           "cold normals (in place: the timed launches keep and restore the same pixels)"})


def least_squares_rows(ctx, n_images):
    """RON's first step: Woodham's least squares over the whole image (``PixelSolver`` with solver ``"none"``, as
    :func:`front_rows` runs it), one launch of its ``solve_kernel`` (the CPU's row split of ``PixelSolver.step``
    left out: one launch, as on CUDA)."""
    from gpps.names import FLAG_WOODHAM_FALLBACK
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    wp = _wp()
    t0 = time.perf_counter()
    sc, mat, lights, img = ball_scene(ctx.size, n_images, ctx.device)
    m = sc.mask
    h, w = m.shape
    ps = PixelSolver(img.shape[:3], sc.camera, lights, mat, replace(SolverConfig(), solver="none", smoothness=0.0),
                     device=ctx.device)
    ctx.keep.append(ps)
    ps.upload(img, m)
    ps.step()
    _sync(ctx)
    ctx.log(f"[chain {ctx.size}] least squares {n_images} images: compile and first solve "
            f"{time.perf_counter() - t0:.1f}s")
    name = f"least_squares_{n_images}img"
    # (recorded once: a plain CPU launch re-packs its struct arguments every time)
    cmd = wp.launch(ps._solve_kernel, dim=(h, w),
                    inputs=[ps.images, ps.mask, ps.valid, ps.depth, ps.noise, ps.cam, ps.lp, ps.mp, ps.prm],
                    outputs=[ps.weights, ps.normals, ps.albedo, ps.residual, ps.iterations, ps.flags, ps.cond],
                    device=ctx.device, record_cmd=True)
    t = _time_or_register(ctx, name, "^solve_kernel__none_", cmd.launch, inner=5)
    if t is not None:
        from gpps.host.metrics import normal_errors
        from gpps.names import ASIDE_WEIGHT

        wt = ps.weights.numpy()[:, m]  # (N, mask pixels)
        fg = ((wt != 0.0) & (wt != ASIDE_WEIGHT)).sum(0).astype(np.float64)
        fallback = (ps.flags.numpy()[m] & int(FLAG_WOODHAM_FALLBACK)) != 0
        fl = np.where(fallback, float(n_images), fg)
        (pb, pf), (ob, of) = COUNTS_CHAIN["least_squares"](n_images, fg, fl)
        mp = int(m.sum())
        row(ctx, name, t, pb * mp + ob * (h * w - mp), float(np.sum(pf)) + of * (h * w - mp),
            extra={"images": n_images, "mask_pixels": mp, "mean_in_fit": float(fg.mean()),
                   "woodham_fallback": int(fallback.sum()),
                   "maen_deg": normal_errors(ps.fetch(("normals",))["normals"], sc.normals, m)["mean"],
                   "summary": f"{mp} px, {fg.mean():.1f}/{n_images} observations in the fit",
                   "note": "solve_kernel of solver 'none' (observation weights, lights' condition, Woodham's "
                           "least squares and its residual), one launch over the image"})


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


PARTS = ("dgmc", "scorer", "solve", "lanes", "bini", "search", "front", "rounds")


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

    d = search.dims
    info = {"candidates": kc, "samples": p, "dims": d}

    def points():
        wp.launch(ms.search_points_kernel, dim=kc,
                  inputs=[search.sim, d, search.lo, search.hi, search.fields, search.base, search.state],
                  outputs=[search.cand, scorer.mats], device=ctx.device)

    t = _time_or_register(ctx, "search_points", "^search_points_kernel_", points, inner=20)
    if t is not None:
        (cb, cf), (lb, _) = COUNTS_CHAIN["search_points"](d)
        row(ctx, "search_points", t, cb * kc + lb, cf * kc, f64=True,
            extra={**info, "summary": f"K={kc}, d={d}",
                   "note": "one thread a candidate: the launch's fixed cost is all of it"})

    def contrib():  # (the first launch reads the rank row's accumulated counts and clears them: then all kept)
        wp.launch(ms.trimmed_contrib_kernel, dim=(kc, p), inputs=[scorer.residual, keep],
                  outputs=[search.before, search.contrib], device=ctx.device)

    t = _time_or_register(ctx, "search_contrib", "^trimmed_contrib_kernel_", contrib, inner=20)
    if t is not None:
        ((cb, cf),) = COUNTS_CHAIN["search_contrib"]()
        row(ctx, "search_contrib", t, cb * kc * p, cf * kc * p, f64=True,
            extra={**info, "keep": keep, "summary": f"K={kc} P={p}",
                   "note": "trimmed_contrib_kernel, every value kept (the counts cleared by the first launch)"})

    lanes = ms.PARTIAL_LANES

    def partial():
        wp.launch(ms.trimmed_partial_kernel, dim=(kc, lanes), inputs=[search.contrib, p],
                  outputs=[search.partial], device=ctx.device)

    t = _time_or_register(ctx, "search_partial", "^trimmed_partial_kernel_", partial, inner=20)
    if t is not None:
        (sb, sf), (lb, lf) = COUNTS_CHAIN["search_partial"]()
        row(ctx, "search_partial", t, sb * kc * p + lb * kc * lanes, sf * kc * p + lf * kc * lanes, f64=True,
            extra={**info, "lanes": lanes, "summary": f"K={kc} x {lanes} lanes, P={p}",
                   "note": "strided partial sums of the contributions (K x PARTIAL_LANES threads)"})

    def energy():
        wp.launch(ms.trimmed_energy_kernel, dim=kc, inputs=[search.partial, keep], outputs=[search.energy],
                  device=ctx.device)

    t = _time_or_register(ctx, "search_energy", "^trimmed_energy_kernel_", energy, inner=20)
    if t is not None:
        ((eb, ef),) = COUNTS_CHAIN["search_energy"](lanes)
        row(ctx, "search_energy", t, eb * kc, ef * kc, f64=True,
            extra={**info, "lanes": lanes, "summary": f"K={kc}, {lanes} partials each",
                   "note": "one thread a candidate: the launch's fixed cost is all of it"})

    def step():  # xatol -1: the condition never clears (every timed launch runs a whole pass); no budget
        wp.launch(ms.search_step_kernel, dim=1, inputs=[search.energy, search.cand, d, 10 ** 9, wp.float64(-1.0)],
                  outputs=[search.sim, search.fsim, search.state, search.cond], device=ctx.device)

    t = _time_or_register(ctx, "search_step", "^search_step_kernel_", step, inner=20)
    if t is not None:
        ((sb, sf),) = COUNTS_CHAIN["search_step"](d)
        row(ctx, "search_step", t, sb, sf, f64=True,
            extra={**info, "cond_after": int(search.cond.numpy()[0]), "summary": f"one thread, d={d}",
                   "note": "search_step_kernel on the same energies launch after launch (steps and shrinks); one "
                           "thread: the launch's fixed cost is all of it"})

    def rest():  # the pass less the scorer's solve (the condition stays set: xatol 0, no budget)
        points()
        rank()
        contrib()
        partial()
        energy()
        wp.launch(ms.search_step_kernel, dim=1, inputs=[search.energy, search.cand, d, 10 ** 9, wp.float64(0.0)],
                  outputs=[search.sim, search.fsim, search.state, search.cond], device=ctx.device)

    if not ctx.driver:
        t = ctx.graph_time(wp, rest, ctx.device, ctx.repeat, inner=10)
        row(ctx, "search_pass_no_solve", t, extra={"candidates": kc, "samples": p,
                                                   "note": "the six launches of a search pass without the solve"})
    ctx.keep.extend([search, scorer])


# ----------------------------------------------------------------------------- DGMC's solved front


def _front_source_work(front, cfg, curv):
    """Per ring pixel of ``front`` (all rings, in list order), replayed on the host from the front's level map and
    curvatures (the kernel's float64 tests, its tolerance products in its order) with Warp's short-circuit `and`
    (:func:`gpps.kernels.front.front_source_kernel`): the steps the widening loop scans, the bound tests evaluated
    in the slots still searching (up to the first that fails), the slots gated in (in bounds, still searching),
    the solved neighbours tested and those whose Gaussian-curvature half of the test held (the mean curvature's
    half evaluated)."""
    pixels = front._plan[1].astype(np.int64)
    level = front.level.numpy()
    gc, mc = front.gc.numpy(), front.mc.numpy()
    h, w = level.shape
    i, j = pixels // w, pixels % w
    di = np.array([-1, 0, 0, 1, -1, -1, 1, 1])  # edge_first_offset's order
    dj = np.array([0, -1, 1, 0, -1, 1, -1, 1])
    a, b = i[:, None] + di, j[:, None] + dj
    inb = (a >= 0) & (a < h) & (b >= 0) & (b < w)
    # bound tests evaluated: a >= 0, a < h, b >= 0, b < w, stopping at the first false
    tests = np.where(a < 0, 1, np.where(a >= h, 2, np.where(b < 0, 3, 4)))
    ac, bc = np.clip(a, 0, h - 1), np.clip(b, 0, w - 1)
    solved = inb & (level[ac, bc] < level[i, j][:, None])
    gp, mp = gc[i, j][:, None], mc[i, j][:, None]
    searching = np.ones(pixels.size, bool)
    steps, bounds, gated, checks, second = (np.zeros(pixels.size) for _ in range(5))
    tt = np.float64(cfg.tolerance)
    slot = np.arange(8)[None, :]
    for _ in range(int(cfg.widen_steps) + 1):
        upto = np.ones((pixels.size, 8), bool)
        hit = np.zeros(pixels.size, bool)
        g_ok = np.zeros((pixels.size, 8), bool)
        if curv:
            g_ok = solved & (np.abs(gc[ac, bc] - gp) <= tt * np.abs(gp))
            ok = g_ok & (np.abs(mc[ac, bc] - mp) <= tt * np.abs(mp))
            hit = searching & ok.any(1)
            upto = np.where(hit[:, None], slot <= ok.argmax(1)[:, None], True)
        live = searching[:, None] & upto
        steps += searching
        bounds += np.where(live, tests, 0).sum(1)
        gated += (live & inb).sum(1)
        checks += (live & solved).sum(1)
        second += (live & g_ok).sum(1)
        searching &= ~hit
        tt = tt * np.float64(cfg.widen_factor)
    return steps, bounds, gated, checks, second


def front_rows(ctx, n_images):
    """DGMC's solved front as RON runs it on the device (round 1: least squares, DGMC's highlights and curvatures,
    the cold solve of the mask, :func:`gpps.pipeline.front.propagate_front_device` on a :class:`DeviceFront`):
    the whole ring loop (host time), then each front kernel one launch as the stage launches it: the sources of
    every ring pixel, on the largest ring the solve mask, the starts and the merge, then the write-back of the
    merged solution and the sources' normals (the ring's solve itself is the pixel solve's kernel: its rows)."""
    from gpps.host.dgmc import DGMCConfig
    from gpps.kernels import front as fk
    from gpps.names import FLAG_FEW_OBSERVATIONS
    from gpps.pipeline.dgmc import DeviceDGMC
    from gpps.pipeline.front import DeviceFront, propagate_front_device
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    wp = _wp()
    t0 = time.perf_counter()
    sc, mat, lights, img = ball_scene(ctx.size, n_images, ctx.device)
    m = sc.mask
    h, w = m.shape
    cfg = DGMCConfig()  # RON's dgmc_config (start="front")
    ps = PixelSolver(img.shape[:3], sc.camera, lights, mat, replace(SolverConfig(), solver="none", smoothness=0.0),
                     device=ctx.device)
    ps.upload(img, m)
    ps.step()  # least squares, DGMC's start
    dgmc = DeviceDGMC(img.shape[:3], config=cfg, device=ctx.device)
    ctx.keep.extend([ps, dgmc])
    dgmc.upload(ps.images, m, ps.normals, lights=lights)  # (RGB: the solver's frame, on the device)
    dgmc.step(starts=False)  # the highlights and the curvatures only (the front picks its sources itself)
    highlight = dgmc.region.numpy().astype(bool)
    ps.set_config(SolverConfig())  # round 1's cold solve of the mask (RON's default solver config)
    ps.step()
    front = DeviceFront(ps)
    ctx.keep.append(front)
    propagate_front_device(ps, m, highlight, gaussian=dgmc.gc, mean=dgmc.mc, config=cfg, keep_better=True,
                           front=front)
    _sync(ctx)
    ring, pixels, sizes, starts, _, curv, _ = front._plan
    n_rings = sizes.size - 1
    if n_rings == 0:
        raise RuntimeError(f"front: no ring on the {ctx.size}^2 x {n_images} ball "
                           f"({int(highlight.sum())} highlight px)")
    k = 1 + int(np.argmax(sizes[1:]))  # the largest ring (the first, in practice)
    a, c = int(starts[k]), int(sizes[k])
    p_all = int(pixels.size)
    ctx.log(f"[chain {ctx.size}] front {n_images} images, {n_rings} rings, {p_all} ring px: least squares, DGMC, "
            f"solve and first front {time.perf_counter() - t0:.1f}s")
    info = {"images": n_images, "mask_pixels": int(m.sum()), "highlight_pixels": int(highlight.sum()),
            "rings": n_rings, "ring_pixels": p_all, "ring": k, "ring_size": c}
    if not ctx.driver:
        reps = max(3, ctx.repeat // 4)
        t = ctx.median_time(lambda: front.step(keep_better=True), lambda: _sync(ctx), reps, warmup=1)
        row(ctx, "front_step", t, extra={**info, "summary": f"{n_rings} rings, {p_all} px",
                                          "note": "DeviceFront.step: the sources, then per ring the mask, starts, "
                                                  "warm solve (PixelSolver.step) and merge (host time, no ratio)"})

    def curvature_in():  # (DeviceFront.upload's two launches: the same values written again)
        for a, buf in ((dgmc.gc, front.gc), (dgmc.mc, front.mc)):
            wp.launch(fk.curvature_in_kernel, dim=(h, w), inputs=[a], outputs=[buf], device=ctx.device)

    t = _time_or_register(ctx, "front_curvature_in", "^curvature_in_kernel_", curvature_in, inner=10, per_launch=2)
    if t is not None:
        ((cb, cf),) = COUNTS_CHAIN["front_curvature_in"]()
        row(ctx, "front_curvature_in", t, cb * 2 * h * w, cf * 2 * h * w, f64=True,
            extra={**info, "summary": f"{h}x{w} px x 2 maps",
                   "note": "DeviceFront.upload: DGMC's device curvatures (GC and MC) rounded to float32, one "
                           "launch a map"})

    def source():
        wp.launch(fk.front_source_kernel, dim=p_all,
                  inputs=[front.pixels, front.level, front.gc, front.mc, int(curv), float(cfg.tolerance),
                          float(cfg.widen_factor), int(cfg.widen_steps)],
                  outputs=[front.sources], device=ctx.device)

    t = _time_or_register(ctx, "front_source", "front_source_kernel", source, inner=10)
    if t is not None:
        steps, bounds, gated, checks, second = _front_source_work(front, cfg, curv)
        ((pb, pf),) = COUNTS_CHAIN["front_source"](steps, bounds, gated, checks, second, int(cfg.widen_steps))
        row(ctx, "front_source", t, pb * p_all, float(np.sum(pf)),
            extra={**info, "mean_steps": float(steps.mean()), "mean_tests": float(checks.mean()),
                   "summary": f"{p_all} px, {steps.mean():.2f} steps, {checks.mean():.1f} tests/px",
                   "note": "every ring pixel, one launch a front step"})

    src = front.sources.numpy()[:p_all]

    def scatter():  # (the solver's mask was cleared by the ring's select_pixels; here it holds the last ring's)
        wp.launch(fk.scatter_mask_kernel, dim=c, inputs=[front.pixels, a, w], outputs=[ps.mask], device=ctx.device)

    t = _time_or_register(ctx, "front_scatter_mask", "scatter_mask_kernel", scatter, inner=20)
    if t is not None:
        ((pb, pf),) = COUNTS_CHAIN["front_scatter_mask"]()
        row(ctx, "front_scatter_mask", t, pb * c, pf * c,
            extra={**info, "summary": f"ring {k}: {c} px",
                   "note": "PixelSolver.select_pixels' scatter on the largest ring (its mask clear not timed); a "
                           "ring's few hundred threads: the launch's fixed cost dominates"})

    def start():
        wp.launch(fk.front_start_kernel, dim=c, inputs=[front.pixels, front.sources, a, w, front.normals],
                  outputs=[ps.normals], device=ctx.device)

    t = _time_or_register(ctx, "front_start", "front_start_kernel", start, inner=20)
    if t is not None:
        (pb, pf), (qb, _) = COUNTS_CHAIN["front_start"]()
        u = int(np.unique(src[a:a + c]).size)
        row(ctx, "front_start", t, pb * c + qb * u, pf * c,
            extra={**info, "distinct_sources": u, "summary": f"ring {k}: {c} px, {u} sources",
                   "note": "the largest ring's starts; its few hundred threads: the launch's fixed cost dominates"})

    few = int(FLAG_FEW_OBSERVATIONS)

    def merge():
        wp.launch(fk.front_merge_kernel, dim=c,
                  inputs=[front.pixels, a, w, 1, few, ps.normals, ps.albedo, ps.residual, ps.iterations, ps.flags],
                  outputs=[front.normals, front.albedo, front.residual, front.flags, front.iterations, front.won],
                  device=ctx.device)

    t = _time_or_register(ctx, "front_merge", "front_merge_kernel", merge, inner=20)
    if t is not None:
        (pb, pf), (wb, _) = COUNTS_CHAIN["front_merge"]()
        q = pixels[a:a + c]
        # the pixels the timed launches kept (the ring's solve already merged: where it won, the residuals are equal)
        wins = int(np.sum((ps.residual.numpy().ravel()[q] < front.residual.numpy().ravel()[q])
                          & ((ps.flags.numpy().ravel()[q] & few) == 0)))
        won = int(front.won.numpy().ravel()[q].sum())
        row(ctx, "front_merge", t, pb * c + wb * wins, pf * c,
            extra={**info, "won_in_step": won, "won_in_timed": wins,
                   "summary": f"ring {k}: {c} px, {won} won in the step",
                   "note": "keep_better on the merged ring: the timed launches keep nothing (the step kept "
                           "won_in_step), its stores of the winners are not timed"})

    t = _time_or_register(ctx, "front_write_back", "front_write_back_kernel", front.write_back, inner=10)
    if t is not None:
        ((pb, pf),) = COUNTS_CHAIN["front_write_back"]()
        row(ctx, "front_write_back", t, pb * h * w, pf * h * w,
            extra={**info, "summary": f"{h}x{w} px", "note": "DeviceFront.write_back: one launch over the image"})

    def source_normals():
        wp.launch(fk.front_source_normals_kernel, dim=p_all, inputs=[front.pixels, front.sources, w, front.normals],
                  outputs=[front.source_normals], device=ctx.device)

    t = _time_or_register(ctx, "front_source_normals", "front_source_normals_kernel", source_normals, inner=20)
    if t is not None:
        (pb, pf), (qb, _) = COUNTS_CHAIN["front_source_normals"]()
        u = int(np.unique(src[src >= 0]).size)
        row(ctx, "front_source_normals", t, pb * p_all + qb * u, pf * p_all,
            extra={**info, "distinct_sources": u, "summary": f"{p_all} px, {u} sources",
                   "note": "DeviceFront.fetch_sources' gather (its two small copies back not timed)"})


# ----------------------------------------------------------------------------- RON's device rounds


def rounds_rows(ctx, n_images):
    """RON's device rounds (:class:`gpps.pipeline.ron_rounds.DeviceRounds`) on the default full-image solve: the
    round's sums (one ``round_sums_kernel`` launch), then the final depth's integration on the device (RON's
    default rounds' integrator: multigrid, ``"normal"`` weighting under perspective, tol 1e-5, fused launches):
    the whole :meth:`DeviceRounds.integrate` (host time) and one ``pcg_iteration`` launch (Taichi)."""
    from gpps._taichi import taichi_device, ti
    from gpps.kernels.ron import ROUND_CHUNK, round_sums_kernel
    from gpps.pipeline.integration import Integrator, IntegratorConfig
    from gpps.pipeline.ron_rounds import DeviceRounds
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    wp = _wp()
    t0 = time.perf_counter()
    sc, mat, lights, img = ball_scene(ctx.size, n_images, ctx.device)
    m = sc.mask
    h, w = m.shape
    ps = PixelSolver(img.shape[:3], sc.camera, lights, mat, SolverConfig(), device=ctx.device)
    ps.upload(img, m)
    ps.step()
    # (RON's integrator: IntegratorConfig(tol=1e-5, weighting="normal" under perspective), on its Taichi device)
    icfg = IntegratorConfig(tol=1e-5, weighting="normal" if sc.camera.is_perspective else "uniform")
    integ = Integrator(m, camera=sc.camera, config=icfg, device=taichi_device(ctx.device))
    rounds = DeviceRounds(ps, m, integ)
    ctx.keep.extend([ps, integ, rounds])
    rounds.upload(np.where(m[..., None], sc.normals, 0.0).astype(np.float32))  # the previous round's normals
    rounds.step()
    got = rounds.fetch()
    _sync(ctx)
    ctx.log(f"[chain {ctx.size}] rounds {n_images} images: scene, solve and first round sums "
            f"{time.perf_counter() - t0:.1f}s")
    mp = int(m.sum())
    info = {"images": n_images, "mask_pixels": mp}
    threads = h * ((w + ROUND_CHUNK - 1) // ROUND_CHUNK)

    def sums():  # (the sums accumulate over the timed launches: the work is the same)
        wp.launch(round_sums_kernel, dim=(h, (w + ROUND_CHUNK - 1) // ROUND_CHUNK),
                  inputs=[rounds.mask, ps.residual, ps.normals, rounds.prev, rounds.sums], device=ctx.device)

    t = _time_or_register(ctx, "rounds_sums", "round_sums_kernel", sums, inner=20)
    if t is not None:
        (mb, mf), (ab, af) = COUNTS_CHAIN["rounds_sums"]()
        row(ctx, "rounds_sums", t, mb * mp + ab * h * w, mf * mp + af * h * w, f64=True,
            extra={**info, "threads": threads, "energy": got["energy"], "change_deg": got["change_deg"],
                   "summary": f"{mp} px, {threads} threads",
                   "note": "DeviceRounds.step's reduction (its sums' clear and the copy into prev not timed)"})

    t1 = time.perf_counter()
    how = "DeviceRounds.integrate"
    try:
        if not rounds.integrates:
            raise ValueError(f"integrator: the device rounds do not build {icfg}")
        rounds.integrate(1.0, into_solver=False)  # (RON's final depth: reference 1 without one)
        last = dict(rounds.last)
    except ImportError as e:  # (CUDA without torch: the same fields and CG from the host's assembly)
        ctx.log(f"[chain {ctx.size}] rounds: {e}; the integrator's host assembly fills the fields")
        how = "Integrator.run (no torch: the host's assembly, the same PCG launches)"
        res = integ.run(ps.fetch(("normals",))["normals"], reference_depth=1.0)
        last = {"iterations": int(res.iterations), "residual": float(res.residual)}
    ti.sync()
    ctx.log(f"[chain {ctx.size}] rounds: compile and first integration {time.perf_counter() - t1:.1f}s")
    info.update(integration=how, pcg_iterations=int(last.get("iterations", 0)),
                pcg_residual=float(last.get("residual", float("nan"))))
    if not ctx.driver and how == "DeviceRounds.integrate":
        reps = max(3, ctx.repeat // 4)
        t = ctx.median_time(lambda: rounds.integrate(1.0, into_solver=False), lambda: (_sync(ctx), ti.sync()),
                            reps, warmup=1)
        row(ctx, "rounds_integrate", t,
            extra={**info, "summary": f"{info['pcg_iterations']} PCG iterations",
                   "note": "DeviceRounds.integrate: assembly, edges, levels, the coarsest pinv (host), the PCG "
                           "to tol (a host read every check_every iterations), depth written (host time, no ratio)"})

    d = integ._ensure_device()
    dg = d["dg"].to_numpy()
    act = [int((dg[:hh, o:o + ww] > 0).sum()) for o, (hh, ww) in zip(d["offs"], d["shapes"])]
    pts = [int(hh * ww) for hh, ww in d["shapes"]]
    nl, nc = len(pts), int(d["nc"])
    lv_info = {"levels": nl, "level_points": pts, "level_active": act, "coarsest_cells": nc}
    start, iteration = integ._pcg_launches(integ._block_sums())
    system = rounds.system if how == "DeviceRounds.integrate" else None
    if system is not None:
        _rounds_assembly_rows(ctx, rounds, integ, d, info, lv_info, start)
    else:
        ctx.log(f"[chain {ctx.size}] rounds: no device assembly ({how}): its rows skipped")
    d["z"].fill(0)  # a fresh solve: the timed iterations are its first ones (the same work as any other)
    start()
    ti.sync()
    t = _time_or_register(ctx, "rounds_pcg_iteration", "^pcg_iteration", iteration, inner=10, taichi=True,
                          per_launch=None)
    if t is not None:
        (ca, ci), *vc = COUNTS_CHAIN["rounds_pcg_iteration"](nc)
        vb, vf = _vcycle_work(vc, act, pts)
        by = ca[0] * act[0] + ci[0] * (pts[0] - act[0]) + vb
        fl = ca[1] * act[0] + ci[1] * (pts[0] - act[0]) + vf
        row(ctx, "rounds_pcg_iteration", t, by, fl,
            extra={**info, **lv_info, "launch": integ._launch(), "block_sums": bool(integ._block_sums()),
                   "summary": f"{h}x{w}, {nl} levels, {by / (h * w):.0f} B {fl / (h * w):.0f} FLOP/px",
                   "note": "one pcg_iteration launch (cg_step, the V-cycle, cg_direction: Taichi tasks); float32 "
                           "fields; some 8 tasks a level, serial ones among them: at small sizes their fixed costs "
                           "dominate; a working set in the last-level cache can beat the DRAM copy bound"})
    if system is not None:
        _rounds_depth_rows(ctx, rounds, integ, d, info)


def _vcycle_work(vc, act, pts):
    """(bytes, FLOPs) of one V-cycle from rounds_pcg_iteration's counts ``vc`` = (per point of a level but the
    coarsest (active, inactive), the restriction per coarse point, the coarsest solve) and the levels' active
    and all points."""
    (va, vi), (rb, rf), (cb, cf) = vc
    by, fl = cb, cf
    for lv in range(len(pts) - 1):
        by += va[0] * act[lv] + vi[0] * (pts[lv] - act[lv]) + rb * pts[lv + 1]
        fl += va[1] * act[lv] + vi[1] * (pts[lv] - act[lv]) + rf * pts[lv + 1]
    return by, fl


def _rounds_assembly_rows(ctx, rounds, integ, d, info, lv_info, start):
    """The device integration's set-up as :meth:`DeviceSystem.step` runs it (Taichi, each call timed on its own):
    the per-pixel assembly, the edges, the levels' coarsening (every level's call), the coarsest level's gather,
    the |b|^2 of the CG's start (residual_norm) and the fused PCG start.  The fields already hold the system: the
    calls recompute it (the statistics ``st`` accumulate over the repeats: counts and their ratio, all the edges
    read)."""
    from gpps._taichi import ti
    from gpps.kernels import poisson as K
    from gpps.kernels import poisson_weighted as KW
    from gpps.pipeline.integration import coarse_alpha

    system = rounds.system
    F = system._F
    cfg = integ.config
    h, w = integ.shape
    cam, wtd = system._cam, system._weighted
    nrm = rounds._view()[0]
    sh, of = d["shapes"], d["offs"]
    pts, act, nc = lv_info["level_points"], lv_info["level_active"], lv_info["coarsest_cells"]
    hw = h * w
    mp = int(integ.mask.sum())

    def taichi_row(name, pattern, fn, by, fl, f64=False, extra=None, inner=10):
        _taichi_row(ctx, name, pattern, fn, by, fl, f64=f64, extra={**info, **(extra or {})}, inner=inner)

    def assemble():
        KW.assemble_pixels(nrm, F["mask"], F["gj"], F["gi"], F["cj"], F["ci"], F["st"], cam[0], wtd, *cam[1:],
                           float(cfg.min_nz), h, w)

    (pb, pf), (qb, qf) = COUNTS_CHAIN["rounds_assemble_pixels"]()
    taichi_row("rounds_assemble_pixels", "^assemble_pixels", assemble, pb * hw + qb * mp, pf * hw + qf * mp, f64=True,
               extra={"perspective": bool(cam[0]), "weighted": bool(wtd), "summary": f"{h}x{w}, {mp} mask px",
                      "note": "assemble_pixels: the normals' checks, steps and confidences (float64 fields)"})

    def edges():
        KW.assemble_edges(F["gj"], F["gi"], F["cj"], F["ci"], F["st"], wtd, d["wx"], d["wy"], d["dg"], d["b"], h, w)

    ti.sync()
    edges()
    ti.sync()
    ve = int((d["wx"].to_numpy()[:h, :w] > 0).sum() + (d["wy"].to_numpy()[:h, :w] > 0).sum())
    (eb, ef), (_, vf) = COUNTS_CHAIN["rounds_assemble_edges"]()
    taichi_row("rounds_assemble_edges", "^assemble_edges", edges, eb * hw, ef * hw + vf * 2 * ve, f64=True,
               extra={"valid_edges": ve, "summary": f"{h}x{w}, {ve} edges",
                      "note": "assemble_edges: level-0 weights, diagonal and right-hand side (each edge computed by "
                              "both its pixels)"})

    alpha = coarse_alpha(not wtd, False)

    def coarsen():
        for k in range(len(sh) - 1):
            KW.coarsen(d["wx"], d["wy"], d["dg"], int(of[k]), sh[k][0], sh[k][1], int(of[k + 1]), sh[k + 1][0],
                       sh[k + 1][1], alpha)

    ((cb, cf),) = COUNTS_CHAIN["rounds_coarsen"]()
    coarse = sum(pts[1:])
    taichi_row("rounds_coarsen", "^coarsen", coarsen, cb * coarse, cf * coarse,
               extra={**lv_info, "summary": f"{len(sh) - 1} calls, {coarse} coarse points",
                      "note": "every level's coarsen call (two tasks each): small launches, their fixed costs "
                              "dominate"})
    hc, wc = sh[-1]

    def gather():
        KW.gather_level(d["wx"], d["wy"], int(of[len(sh) - 1]), hc, wc, F["lvl"])

    ((gb, gf),) = COUNTS_CHAIN["rounds_gather_level"]()
    taichi_row("rounds_gather_level", "^gather_level", gather, gb * hc * wc, gf * hc * wc,
               extra={"summary": f"{hc}x{wc} cells", "note": "the coarsest level's weights for the host's "
                                                              "pseudo-inverse (read back after it: not timed)"})
    blk = integ._block_sums()

    def residual_norm():  # (|b|^2: x = r, cleared by the integrator first; the work does not depend on x)
        K.residual_norm(d["r"], d["b"], d["q"], d["wx"], d["wy"], d["dg"], d["sc"], h, w, blk)

    (ra, ri) = COUNTS_CHAIN["rounds_residual_norm"]()
    taichi_row("rounds_residual_norm", "^residual_norm", residual_norm, ra[0] * act[0] + ri[0] * (pts[0] - act[0]),
               ra[1] * act[0] + ri[1] * (pts[0] - act[0]),
               extra={"active": act[0], "summary": f"{h}x{w}, {act[0]} active",
                      "note": "residual_norm as the CG's start runs it for |b|^2 (the sum's serial store too)"})
    ((sa, si), (db, df)), vc = COUNTS_CHAIN["rounds_pcg_start"](), COUNTS_CHAIN["rounds_pcg_iteration"](nc)[1:]
    vb, vf = _vcycle_work(vc, act, pts)
    by = sa[0] * act[0] + si[0] * (pts[0] - act[0]) + db * pts[0] + vb
    fl = sa[1] * act[0] + si[1] * (pts[0] - act[0]) + df * pts[0] + vf
    taichi_row("rounds_pcg_start", "^pcg_start", start, by, fl,
               extra={**lv_info, "summary": f"{h}x{w}, {len(pts)} levels",
                      "note": "one pcg_start launch (cg_start, the first V-cycle, cg_first_direction: Taichi tasks)"})


def _rounds_depth_rows(ctx, rounds, integ, d, info):
    """The device integration's depth out, as :meth:`DeviceSystem._solve_assembled` runs it after the CG (Taichi,
    each call timed on its own): the components' sums, the perspective's exp sums, the depth's write and fill."""
    from gpps.kernels import poisson_weighted as KW

    system = rounds.system
    F = system._F
    h, w = integ.shape
    hw = h * w
    persp = system._cam[0]
    out = rounds._view()[1]
    mp = int(integ.mask.sum())
    valid = int(((F["cj"].to_numpy() > 0) & (F["lab"].to_numpy() >= 0)).sum())
    xinfo = {**info, "valid_pixels": valid, "summary": f"{h}x{w}, {valid} valid px"}

    def taichi_row(name, pattern, fn, by, fl, note):
        _taichi_row(ctx, name, pattern, fn, by, fl, f64=True, extra={**xinfo, "note": note})

    def sums():
        KW.component_sums(d["z"], F["cj"], F["lab"], F["csum"], F["ccnt"], F["cmax"], F["cmin"], F["st"], h, w)

    (pb, pf), (vb, vf) = COUNTS_CHAIN["rounds_component_sums"]()
    taichi_row("rounds_component_sums", "^component_sums", sums, pb * hw + vb * valid, pf * hw + vf * valid,
               "component_sums: the clear of the H W component fields, the per-component sums (atomics), the span")
    if persp:
        def dexp():
            KW.depth_exp(d["z"], F["cj"], F["lab"], F["cmax"], F["cden"], h, w)

        (pb, pf), (vb, vf) = COUNTS_CHAIN["rounds_depth_exp"]()
        taichi_row("rounds_depth_exp", "^depth_exp", dexp, pb * hw + vb * valid, pf * hw + vf * valid,
                   "depth_exp: the per-component sums of exp(z - max z) (perspective)")

    ref = 1.0

    def write():
        KW.depth_write(d["z"], F["cj"], F["lab"], F["csum"], F["ccnt"], F["cmax"], F["cden"], F["st"], out, persp,
                       ref, 1, h, w)

    (pb, pf), (vb, vf) = COUNTS_CHAIN["rounds_depth_write"]()
    taichi_row("rounds_depth_write", "^depth_write", write, pb * hw + vb * valid, pf * hw + vf * valid,
               "depth_write: the depth of the valid pixels (float32) and the fill value's sums")

    def fill():
        KW.depth_fill(F["cj"], F["lab"], F["mask"], F["st"], out, ref, 1.0, 1, h, w)

    (pb, pf), (ob, _), (mb, mf) = COUNTS_CHAIN["rounds_depth_fill"]()
    taichi_row("rounds_depth_fill", "^depth_fill", fill, pb * hw + ob * (hw - mp) + mb * mp, pf * hw + mf * mp,
               "depth_fill: outside the mask and the dropped pixels")


def bench_chain(ctx, parts, images, samples, candidates, errors):
    """All chain rows of ``parts`` (each part's failure is recorded in ``errors`` and the others go on)."""
    import traceback

    jobs = {
        "dgmc": lambda: dgmc_rows(ctx, images),
        "scorer": lambda: [(scorer_rows(ctx, n, samples, candidates), scorer_sample_rows(ctx, n, samples, candidates))
                           for n in dict.fromkeys((images, 3))],
        "solve": lambda: ([(pixel_solve_rows(ctx, n), pixel_solve_warm_rows(ctx, n), least_squares_rows(ctx, n))
                           for n in dict.fromkeys((images, 3))], merge_saved_rows(ctx)),
        "lanes": lambda: (scorer_lanes_rows(ctx, images), pixel_solve_lanes_rows(ctx, images)),
        "bini": lambda: bini_rows(ctx),
        "search": lambda: search_rows(ctx, samples),
        "front": lambda: front_rows(ctx, images),
        "rounds": lambda: rounds_rows(ctx, images),
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

"""Batched per-pixel solve for the material search: K candidate materials x P sample pixels in one launch.

Device math only; buffers and launches live in :mod:`gpps.pipeline.material`.

RON's photometric material update (``gpps.flows.ron``, step 4) scores a
candidate material ``m`` by the trimmed mean of the squared per-pixel
residuals of the variable-projection fit (seed 4.1-4.2; see
:mod:`gpps.kernels.solve`)::

    E(m) = 1/|S'| sum_(p in S') r_p(m)^2,   r_p(m)^2 = 2 min_(n, kd) F_p(n, kd; m) / (3 sum_k |w_k|)

over the sample pixels ``S`` (``S'``: all but the worst ``trim`` fraction).
Every ``r_p(m)`` is the per-pixel solve of :func:`gpps.kernels.solve_kernels.solve_kernel_for`
with the material ``m``; nothing in a pixel's solve depends on another pixel
(the fit runs without the neighbour pass and the smoothness term).  So the
pixels are gathered once into a compact *strip* and the (candidate, pixel)
pairs are independent threads:

* :data:`prepare_samples_kernel` (dim P, once per upload): the material-free
  part of ``solve_kernel`` for each sample pixel: its surface point and view
  direction (2.33, at its true row and column), observation weights (shadow,
  saturation, caller's ``valid``, the noise test of the lit count), the
  lighting-sensitivity flags (3.13) and Woodham's least-squares start.
* the batched kernel of :func:`get_batched_kernel` (dim (K, P), once per search
  step): multi-start nonlinear least squares and (robust builds) IRLS rounds,
  candidate ``c`` with ``mats[c]``; outputs (K, P).

Layout.  The per-pixel functions index ``images[k, px.i, px.j]`` and
``weights[k, px.i, px.j]``.  Here ``px.i`` is the candidate ``c`` and ``px.j``
the sample index ``p``; ``images`` is an (N, K, P) *view* with stride 0 along
the candidate axis of the (N, 1, P) strip (one copy of the observations serves
every candidate).  ``weights`` is the same kind of view of the (N, 1, P) base
weights when the loss is not robust (the solve only reads them), and an
(N, K, P) buffer of its own when it is (IRLS rewrites a pixel's weights per
candidate; the kernel first copies the base weights into its column).  The
pixel's point and view direction come precomputed in the :class:`Pixel`, so
``px.i`` / ``px.j`` are only array indices, never camera coordinates.

Specialisation as in :mod:`gpps.kernels.solve`: one Warp module per
``(method, brdf, robust)`` built from :func:`gpps.kernels.solve_methods.solver_funcs`
with ``wp.static`` conditions (a monolithic kernel took more than 13 minutes
to compile on CUDA); the material's *parameters* are run-time values, so all
candidates of one model share a build.  Because the same device functions run
on the same float32 inputs, a pixel's residual equals the one
``PixelSolver`` computes, up to the code generator's choices in another
module (inlining, FMA contraction).  On the CPU the pixels-parallel build lives in the
solve kernels' own module (:func:`gpps.kernels.solve.batched_in_solve_module`).
"""

import warp as wp

from gpps import names

from gpps.kernels.brdf import (
    CameraParams,
    LightParams,
    MaterialParams,
    pixel_point,
    view_dir,
)
from gpps.kernels.solve import module_name as _solve_module_name
from gpps.kernels.solve import cache_suffix, get_solve_batched_kernel, specialisation_key
from gpps.kernels.solve_common import (
    FLAG_FEW_OBSERVATIONS,
    FLAG_ILL_CONDITIONED,
    FLAG_WOODHAM_FALLBACK,
    SolverParams,
    cond_frobenius,
    grey,
    grey_max,
    light_gram,
    pick_start,
    pixel_at,
    store_solution,
    store_solution_lanes,
)
from gpps.kernels.solve_kernels import least_squares_start, observation_weights
from gpps.kernels.solve_methods import solver_funcs

__all__ = [
    "prepare_samples_kernel",
    "gather_samples_kernel",
    "gather_start_kernel",
    "tile_reset_kernel",
    "tile_score_kernel",
    "tile_pick_kernel",
    "tile_samples_kernel",
    "get_batched_kernel",
    "get_batched_starts_kernels",
    "batched_module_name",
]

# "no pixel yet" in a tile's arg-min slot (larger than any flat pixel index)
TILE_NONE = wp.constant(2147483647)


@wp.func
def strip_pixel(c: int, p: int, point: wp.vec3, view: wp.vec3, prm: SolverParams):
    """The :class:`Pixel` of candidate ``c`` and sample ``p``: array indices (c, p), precomputed point and view."""
    return pixel_at(c, p, point, view, prm)


@wp.kernel(enable_backward=False)
def prepare_samples_kernel(
    strip: wp.array3d(dtype=wp.vec3),
    strip_valid: wp.array3d(dtype=wp.uint8),
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    sample_depth: wp.array(dtype=wp.float32),
    noise: wp.array(dtype=wp.float32),
    cam: CameraParams,
    lights: LightParams,
    prm: SolverParams,
    base_weights: wp.array3d(dtype=wp.float32),
    points: wp.array(dtype=wp.vec3),
    views: wp.array(dtype=wp.vec3),
    ninit: wp.array(dtype=wp.vec3),
    gmax: wp.array(dtype=wp.float32),
    base_flags: wp.array(dtype=wp.int32),
    cond: wp.array(dtype=wp.float32),
):
    """The material-free part of ``solve_kernel`` for sample pixel ``p`` (dim P).

    Args:
        strip: (N, 1, P) RGB observations of the sample pixels (images divided by
            the light intensities when the lights carry unit intensity).
        strip_valid: (N, 1, P) 1 where the caller keeps the observation.
        rows, cols: (P,) the sample pixels' row and column in the image.
        sample_depth: (P,) depth > 0 (scene units) of each sample pixel.
        noise: (N,) noise standard deviation of each image's grey values (0: unknown).
        base_weights: (N, 1, P) out: observation weights (1 used, -1 dark, 0 dropped).
        points: (P,) out: surface point (2.33, gpps frame, scene units).
        views: (P,) out: unit view direction.
        ninit: (P,) out: Woodham's least-squares normal (the first start).
        gmax: (P,) out: brightest grey value.
        base_flags: (P,) out: FLAG_FEW_OBSERVATIONS / ILL_CONDITIONED / WOODHAM_FALLBACK bits.
        cond: (P,) out: Frobenius condition number of the valid lights' Gram matrix (3.13).
    """
    p = wp.tid()
    nl_ = lights.count
    point = pixel_point(cam, rows[p], cols[p], sample_depth[p])
    px = strip_pixel(0, p, point, view_dir(cam, point), prm)
    g = grey_max(strip, 0, p, nl_)
    ninfo = observation_weights(strip, strip_valid, noise, prm, 0, p, nl_, g, base_weights)
    flag = int(0)
    if ninfo < 3:
        flag = flag | FLAG_FEW_OBSERVATIONS
    cnd = cond_frobenius(light_gram(base_weights, 0, p, px.p, lights))
    if cnd > prm.cond_threshold:
        flag = flag | FLAG_ILL_CONDITIONED
    use_all = int(0)
    if cnd >= 1.0e29:
        use_all = 1
        flag = flag | FLAG_WOODHAM_FALLBACK
    n0, kdw = least_squares_start(strip, base_weights, px, lights, use_all, 0)
    points[p] = px.p
    views[p] = px.v
    ninit[p] = n0
    gmax[p] = g
    base_flags[p] = flag
    cond[p] = cnd


@wp.kernel(enable_backward=False)
def gather_start_kernel(
    normals: wp.array2d(dtype=wp.vec3),
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    ninit: wp.array(dtype=wp.vec3),
    nwarm: wp.array(dtype=wp.vec3),
):
    """Warm starts of the sample pixels from a frame's normals (dim P), nothing through the host.

    Args:
        normals: (H, W) a solve's normals (e.g. :class:`PixelSolver`'s buffer).
        rows, cols: (P,) the sample pixels' row and column.
        ninit: (P,) the cold start (Woodham's normal), taken where the frame's normal is not
            a unit vector (a pixel the solve left at zero): the host path's ``check_unit`` refuses those.
        nwarm: (P,) out: the start normals.
    """
    p = wp.tid()
    n = normals[rows[p], cols[p]]
    ln = wp.length(n)
    if ln > 0.999 and ln < 1.001:
        nwarm[p] = n
    else:
        nwarm[p] = ninit[p]


@wp.kernel(enable_backward=False)
def gather_samples_kernel(
    images: wp.array3d(dtype=wp.vec3),
    valid: wp.array3d(dtype=wp.uint8),
    depth: wp.array2d(dtype=wp.float32),
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    use_valid: int,
    use_depth: int,
    strip: wp.array3d(dtype=wp.vec3),
    strip_valid: wp.array3d(dtype=wp.uint8),
    sample_depth: wp.array(dtype=wp.float32),
):
    """The device form of :meth:`MaterialScorer.upload`'s gather: sample ``p`` from frame buffers (dim P).

    Args:
        images: (N, H, W) RGB observations of the frame (e.g. a stream's converted frame).
        valid: (N, H, W) 1 where the observation is used.
        depth: (H, W) depth > 0 (scene units).
        rows, cols: (P,) the sample pixels' row and column.
        use_valid, use_depth: 0: ``valid`` / ``depth`` are not read and ``strip_valid`` /
            ``sample_depth`` not written (the caller filled them with 1).
        strip: (N, 1, P) out: their observations.
        strip_valid: (N, 1, P) out: their ``valid`` flags.
        sample_depth: (P,) out: their depth.
    """
    p = wp.tid()
    i = rows[p]
    j = cols[p]
    for k in range(images.shape[0]):
        strip[k, 0, p] = images[k, i, j]
        if use_valid != 0:
            strip_valid[k, 0, p] = valid[k, i, j]
    if use_depth != 0:
        sample_depth[p] = depth[i, j]


@wp.kernel(enable_backward=False)
def tile_reset_kernel(best: wp.array(dtype=wp.float32), pick: wp.array(dtype=wp.int32)):
    """Empty every tile's running maximum and arg-max before :data:`tile_score_kernel` (dim T)."""
    t = wp.tid()
    best[t] = -1.0
    pick[t] = TILE_NONE


@wp.func
def _tile_of(i: int, j: int, box: wp.vec4i, tiles_j: int, tile_h: int, tile_w: int) -> int:
    """Tile of pixel (i, j) in a grid of ``tile_h x tile_w`` tiles over ``box = (i0, j0, i1, j1)``; -1 outside."""
    if i < box[0] or j < box[1] or i >= box[2] or j >= box[3]:
        return -1
    return ((i - box[0]) // tile_h) * tiles_j + (j - box[1]) // tile_w


@wp.kernel(enable_backward=False)
def tile_score_kernel(
    images: wp.array3d(dtype=wp.vec3),
    mask: wp.array2d(dtype=wp.uint8),
    box: wp.vec4i,
    tiles_j: int,
    tile_h: int,
    tile_w: int,
    score: wp.array2d(dtype=wp.float32),
    best: wp.array(dtype=wp.float32),
):
    """Highlight score of every mask pixel, and each tile's maximum (dim (H, W)).

    The score is the pixel's brightest grey value over its N observations: the
    specular lobe peaks there (RON samples highlight pixels first, 4.1.10).

    Args:
        images: (N, H, W) RGB observations.
        mask: (H, W) 1 inside the mask.
        box, tiles_j, tile_h, tile_w: the tile grid (:func:`_tile_of`).
        score: (H, W) out: the score (-1 outside the mask and the grid).
        best: (T,) in/out: each tile's maximum score (reset by :data:`tile_reset_kernel`).
    """
    i, j = wp.tid()
    s = float(-1.0)
    t = _tile_of(i, j, box, tiles_j, tile_h, tile_w)
    if mask[i, j] != 0 and t >= 0:
        for k in range(images.shape[0]):
            s = wp.max(s, grey(images[k, i, j]))
        wp.atomic_max(best, t, s)
    score[i, j] = s


@wp.kernel(enable_backward=False)
def tile_pick_kernel(
    score: wp.array2d(dtype=wp.float32),
    box: wp.vec4i,
    tiles_j: int,
    tile_h: int,
    tile_w: int,
    best: wp.array(dtype=wp.float32),
    pick: wp.array(dtype=wp.int32),
):
    """Each tile's arg-max: the smallest flat index (row-major) among its pixels with the tile's maximum
    score (dim (H, W); deterministic: ties go to the first pixel in raster order)."""
    i, j = wp.tid()
    s = score[i, j]
    if s >= 0.0:
        t = _tile_of(i, j, box, tiles_j, tile_h, tile_w)
        if s == best[t]:
            wp.atomic_min(pick, t, i * score.shape[1] + j)


@wp.kernel(enable_backward=False)
def tile_samples_kernel(
    pick: wp.array(dtype=wp.int32),
    fallback_rows: wp.array(dtype=wp.int32),
    fallback_cols: wp.array(dtype=wp.int32),
    width: int,
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
):
    """Sample slot ``t`` = tile ``t``'s pick, or the fixed fallback pixel of the slot when the tile has no
    mask pixel (dim T)."""
    t = wp.tid()
    q = pick[t]
    if q == TILE_NONE:
        rows[t] = fallback_rows[t]
        cols[t] = fallback_cols[t]
    else:
        rows[t] = q // width
        cols[t] = q - (q // width) * width


def batched_kernel_for(robust, solve_pixel, module, sfx: str, lanes: bool = False):
    """``solve_batched_kernel``: candidates x sample pixels, one thread (or one block) a (candidate, pixel) pair.

    Args:
        robust: ``"none"``, ``"huber"`` or ``"cauchy"`` (the normalised key's loss).
        solve_pixel: the nonlinear solve (:func:`gpps.kernels.solve_methods.solve_pixel_for`).
        module: Warp module of the kernel.
        sfx: key suffix of the kernel.
        lanes: the lights-parallel build, launched with ``wp.launch_tiled(dim=(K, chunk),
            block_dim=B)``: the B lanes of a block share one (candidate, pixel) solve, each
            taking every B-th light (``solve_pixel`` must be the lanes build too).
    """

    @wp.kernel(name="solve_batched_kernel" + sfx, module=module, enable_backward=False)
    def solve_batched_kernel(
        strip_k: wp.array3d(dtype=wp.vec3),
        base_weights: wp.array3d(dtype=wp.float32),
        points: wp.array(dtype=wp.vec3),
        views: wp.array(dtype=wp.vec3),
        ninit: wp.array(dtype=wp.vec3),
        gmax: wp.array(dtype=wp.float32),
        base_flags: wp.array(dtype=wp.int32),
        lights: LightParams,
        mats: wp.array(dtype=MaterialParams),
        prm: SolverParams,
        first: int,
        weights_k: wp.array3d(dtype=wp.float32),
        normals_k: wp.array2d(dtype=wp.vec3),
        albedo_k: wp.array2d(dtype=wp.vec3),
        residual_k: wp.array2d(dtype=wp.float32),
        iterations_k: wp.array2d(dtype=wp.int32),
        flags_k: wp.array2d(dtype=wp.int32),
    ):
        """Solve sample pixel ``first + t`` with candidate material ``mats[c]`` (dim (K, chunk)).

        Args:
            strip_k: (N, K, P) observations, a stride-0 view of the (N, 1, P) strip along K.
            base_weights: (N, 1, P) observation weights of :data:`prepare_samples_kernel`.
            points, views, ninit, gmax, base_flags: (P,) from :data:`prepare_samples_kernel`.
            mats: (K,) candidate materials (one reflectance model: this build's).
            first: index of the first sample pixel of this launch (a chunk of the pixels).
            weights_k: (N, K, P) the weights the solve reads: a stride-0 view of
                ``base_weights`` (robust "none"), or a buffer of its own that each
                thread fills from ``base_weights`` and the IRLS rounds rewrite.
            normals_k: (K, P) out: unit normals.
            albedo_k: (K, P) out: RGB albedo kd.
            residual_k: (K, P) out: RMS weighted residual per valid observation and
                channel (``solve_kernel``'s ``residual``), image units.
            iterations_k: (K, P) out: cost evaluations used.
            flags_k: (K, P) out: FLAG_* bits (``base_flags`` plus FLAG_NOT_CONVERGED).
        """
        if wp.static(lanes):
            c, t, lane = wp.tid()
            p = first + t
            nl_ = lights.count
            nb = wp.block_dim()
            if wp.static(robust != "none"):
                for k in range(lane, nl_, nb):  # each lane its own lights: it alone reweights them
                    weights_k[k, c, p] = base_weights[k, 0, p]
            px = strip_pixel(c, p, points[p], views[p], prm)
            px.lane = lane
            px.lanes = nb
            sol = solve_pixel(ninit[p], gmax[p], strip_k, weights_k, px, lights, mats[c], prm)
            store_solution_lanes(sol, base_flags[p], weights_k, px, nl_, normals_k, albedo_k, residual_k,
                                 iterations_k, flags_k)
        else:
            c, t = wp.tid()
            p = first + t
            nl_ = lights.count
            if wp.static(robust != "none"):
                for k in range(nl_):
                    weights_k[k, c, p] = base_weights[k, 0, p]
            px = strip_pixel(c, p, points[p], views[p], prm)
            sol = solve_pixel(ninit[p], gmax[p], strip_k, weights_k, px, lights, mats[c], prm)
            store_solution(sol, base_flags[p], weights_k, px, nl_, normals_k, albedo_k, residual_k, iterations_k,
                           flags_k)

    return solve_batched_kernel


def batched_starts_kernels_for(robust, one_start, finish_pixel, module, sfx: str):
    """The starts-parallel form of ``solve_batched_kernel`` (cold steps on CUDA, where a launch costs its slowest
    thread): ``solve_starts_kernel`` (dim (K, chunk, S)) runs start ``s`` of candidate ``c`` and pixel ``p`` in
    a thread of its own and writes its :class:`StartResult` to scratch (K, P, S) buffers;
    ``solve_finish_kernel`` (dim (K, chunk)) picks the best start in start order by the rule of
    :func:`gpps.kernels.solve_methods.solve_pixel_for` (the first strictly lower cost facing the camera), adds
    up the evaluations, then runs ``finish_pixel`` (the least-squares start when none faced the camera, the
    IRLS rounds) and stores the solution as the one-thread kernel does.  The same device functions on the same
    inputs: each start's result equals the sequential loop's (the starts read the base weights, which is what
    the loop's copy holds before any IRLS round)."""

    @wp.kernel(name="solve_starts_kernel" + sfx, module=module, enable_backward=False)
    def solve_starts_kernel(
        strip_k: wp.array3d(dtype=wp.vec3),
        base_k: wp.array3d(dtype=wp.float32),
        points: wp.array(dtype=wp.vec3),
        views: wp.array(dtype=wp.vec3),
        ninit: wp.array(dtype=wp.vec3),
        lights: LightParams,
        mats: wp.array(dtype=MaterialParams),
        prm: SolverParams,
        first: int,
        start_n: wp.array3d(dtype=wp.vec3),
        start_kd: wp.array3d(dtype=wp.vec3),
        start_cost: wp.array3d(dtype=wp.float32),
        start_iters: wp.array3d(dtype=wp.int32),
        start_conv: wp.array3d(dtype=wp.int32),
    ):
        """Start ``s`` of sample pixel ``first + t`` with candidate ``mats[c]`` (dim (K, chunk, S)); ``base_k``:
        the (N, K, P) stride-0 view of the base weights."""
        c, t, st = wp.tid()
        p = first + t
        px = strip_pixel(c, p, points[p], views[p], prm)
        res = one_start(st, ninit[p], strip_k, base_k, px, lights, mats[c], prm)
        start_n[c, p, st] = res.n
        start_kd[c, p, st] = res.kd
        start_cost[c, p, st] = res.cost
        start_iters[c, p, st] = res.iters
        start_conv[c, p, st] = res.converged

    @wp.kernel(name="solve_finish_kernel" + sfx, module=module, enable_backward=False)
    def solve_finish_kernel(
        strip_k: wp.array3d(dtype=wp.vec3),
        base_weights: wp.array3d(dtype=wp.float32),
        points: wp.array(dtype=wp.vec3),
        views: wp.array(dtype=wp.vec3),
        ninit: wp.array(dtype=wp.vec3),
        gmax: wp.array(dtype=wp.float32),
        base_flags: wp.array(dtype=wp.int32),
        lights: LightParams,
        mats: wp.array(dtype=MaterialParams),
        prm: SolverParams,
        first: int,
        start_n: wp.array3d(dtype=wp.vec3),
        start_kd: wp.array3d(dtype=wp.vec3),
        start_cost: wp.array3d(dtype=wp.float32),
        start_iters: wp.array3d(dtype=wp.int32),
        start_conv: wp.array3d(dtype=wp.int32),
        weights_k: wp.array3d(dtype=wp.float32),
        normals_k: wp.array2d(dtype=wp.vec3),
        albedo_k: wp.array2d(dtype=wp.vec3),
        residual_k: wp.array2d(dtype=wp.float32),
        iterations_k: wp.array2d(dtype=wp.int32),
        flags_k: wp.array2d(dtype=wp.int32),
    ):
        """The best of the starts of :data:`solve_starts_kernel`, then ``finish_pixel`` and the store (dim (K, chunk))."""
        c, t = wp.tid()
        p = first + t
        nl_ = lights.count
        if wp.static(robust != "none"):
            for k in range(nl_):
                weights_k[k, c, p] = base_weights[k, 0, p]
        px = strip_pixel(c, p, points[p], views[p], prm)
        best, total = pick_start(start_n, start_kd, start_cost, start_iters, start_conv, c, p, wp.max(prm.starts, 1),
                                 ninit[p], px.v)
        sol = finish_pixel(best, total, ninit[p], gmax[p], strip_k, weights_k, px, lights, mats[c], prm)
        store_solution(sol, base_flags[p], weights_k, px, nl_, normals_k, albedo_k, residual_k, iterations_k,
                       flags_k)

    return solve_starts_kernel, solve_finish_kernel


_BATCHED: dict = {}
_BATCHED_STARTS: dict = {}


def batched_module_name(method, brdf, robust, lanes: bool = False, cache: int = names.SOLVE_TERM_CACHE) -> str:
    """Name of the Warp module holding the batched kernel of one specialisation (``cache``:
    :func:`gpps.kernels.solve.term_cache_size`)."""
    tag = _solve_module_name(method, brdf, robust).rsplit(".", 1)[1]
    return f"gpps.kernels.solve_batched.{tag}" + ("_lanes" if lanes else "") + cache_suffix(cache)


def get_batched_starts_kernels(method, brdf, robust="none"):
    """The starts-parallel pair ``(solve_starts_kernel, solve_finish_kernel)`` of
    :func:`batched_starts_kernels_for` for one solver, model and loss, in a Warp module of its own
    (:func:`batched_module_name` + ``"_starts"``), built once and cached."""
    key = specialisation_key(method, brdf, robust)
    if None in key or key[0] == "none":
        raise ValueError(f"method, brdf, robust: expected a nonlinear solver and fixed choices, got {key}")
    k = _BATCHED_STARTS.get(key)
    if k is None:
        name = batched_module_name(*key) + "_starts"
        sfx = "__starts_" + name.rsplit(".", 1)[1]
        module = wp.get_module(name)
        funcs = solver_funcs(*key, module, sfx)
        k = batched_starts_kernels_for(key[2], funcs.one_start, funcs.finish_pixel, module, sfx)
        _BATCHED_STARTS[key] = k
    return k


def get_batched_kernel(method, brdf, robust="none", lanes: bool = False, cache: int = names.SOLVE_TERM_CACHE,
                       in_solve_module: bool = False):
    """The batched solve kernel specialised for one solver, reflectance model and robust loss.

    Args:
        method: ``"lm"``, ``"dogleg"`` or ``"bfgs"`` (solver ``"none"`` does not
            depend on the material: nothing to batch).
        brdf: a :data:`gpps.names.BRDF_NAMES` name.
        robust: ``"none"``, ``"huber"`` or ``"cauchy"``; ``"none"`` emits no IRLS
            round (``prm.irls_rounds`` must be 0) and never writes ``weights_k``.
        lanes: the lights-parallel build (:func:`batched_kernel_for`; launch it tiled).
        cache: the lights the evaluation keeps between its passes (:func:`gpps.kernels.solve.term_cache_size`).
        in_solve_module: the pixels-parallel build in the module of the solve kernels of the same specialisation
            (:func:`gpps.kernels.solve.get_solve_batched_kernel`; the rule:
            :func:`gpps.kernels.solve.batched_in_solve_module`).  Not for ``lanes``.

    Built once per key and cached, in a Warp module of its own
    (:func:`batched_module_name`) unless ``in_solve_module``, compiled on first launch.
    """
    key = specialisation_key(method, brdf, robust)
    if None in key or key[0] == "none":
        raise ValueError(f"method, brdf, robust: expected a nonlinear solver and fixed choices, got {key}")
    lanes = bool(lanes)
    cache = int(cache)
    if in_solve_module:
        if lanes:
            raise ValueError("in_solve_module: expected the pixels-parallel build (lanes=False)")
        return get_solve_batched_kernel(*key, cache=cache)
    k = _BATCHED.get((key, lanes, cache))
    if k is None:
        name = batched_module_name(*key, lanes=lanes, cache=cache)
        sfx = "__batched_" + name.rsplit(".", 1)[1]
        module = wp.get_module(name)
        funcs = solver_funcs(*key, module, sfx, lanes=lanes, cache=cache)
        k = batched_kernel_for(key[2], funcs.solve_pixel, module, sfx, lanes=lanes)
        _BATCHED[(key, lanes, cache)] = k
    return k

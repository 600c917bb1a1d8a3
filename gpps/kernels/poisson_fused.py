"""Fused Taichi kernels of the streaming Poisson integrator: few launches per frame.

Same discrete problem, field layout and multigrid as :mod:`gpps.kernels.poisson`
(packed levels side by side, 2x2 aggregation, damped Jacobi smoothing, an exact
pseudo-inverse on the coarsest level, float64 accumulators for the conjugate
gradient scalars), but the level geometry is fixed when the kernels are built,
so a whole preconditioned-CG iteration (``A p``, the updates, every level of
the V-cycle, the new direction) is *one* Taichi kernel: its top-level loops are
unrolled with ``ti.static`` and run as consecutive parallel tasks of a single
launch.  At real-time rates the Python launch (about 20-45 us a kernel on an
H200, see ``../shared/device/README.md``) otherwise costs more than the work.
Each task still costs about 3 us of device time and 5 us of host time, so on
CUDA the small levels can run as *one* persistent task whose phases meet at
software grid barriers (``persistent``, ``hybrid``: :mod:`gpps.kernels.poisson_fused_persistent`;
about 2 us a barrier on an H100, ``perf/taichi_grid_barrier.py``).

:func:`make_fused` builds the kernels for one set of fields and one geometry;
the fields are closed over (not passed), so each instance of
:class:`gpps.pipeline.integration_device.StreamIntegrator` compiles its own.
It gathers the fields and the geometry's constants in a namespace ``ns`` and
hands it to factories by topic, each adding its ti.funcs to ``ns`` for the
next: reductions, the depth update and the finish
(:mod:`gpps.kernels.poisson_fused_sums`), the V-cycle
(:mod:`gpps.kernels.poisson_fused_vcycle`), the right-hand side, the CG and
the one-launch frame (here), the persistent frames
(:mod:`gpps.kernels.poisson_fused_persistent`).  Profiling kernels built from
the same parts (``ns`` is returned as ``parts``) live in
``perf/_fused_variants.py``.  Only device code lives here.
"""

from types import SimpleNamespace

from gpps._taichi import ti
from gpps.kernels.poisson import ALPHA, PQ, RR, RZ, RZN, _mul, _neigh, _sq, pixel_steps
from gpps.kernels.poisson_fused_persistent import persistent_builders
from gpps.kernels.poisson_fused_sums import finish_funcs, reduce_funcs, update_funcs, warp_funcs
from gpps.kernels.poisson_fused_vcycle import level_funcs, vcycle_funcs


def make_fused(F: dict, geo: list, npairs: int, omega: float, nc: int, perspective: bool):
    """Build the fused kernels over the fields ``F`` for the level geometry ``geo``.

    Args:
        F: Taichi fields: ``wx, wy, dg, e, f, t`` (packed levels, (H, sum W_k)),
            ``z, b, r, p, q`` (level 0, (H, W)), ``sc`` (f64 scalars), ``pinv``,
            ``cidx`` (coarsest level), ``red`` (level-0 scratch), ``part``
            (f64, (ceil(H / 8), W): reduction partials), ``lab`` (component label per pixel, -1
            outside), ``csum, cden`` (f64 per-component accumulators), ``ccnt``
            (pixels per component).
        geo: ``[(off, h, w), ...]`` per level, level 0 first.
        npairs: Jacobi sweep pairs before and after each coarse correction.
        omega: Jacobi damping.
        nc: active cells of the coarsest level.
        perspective: the unknown is log-depth (PPN gradients, depth = exp).

    Returns:
        dict of kernels: ``rhs_only(nrm, fx, fy, cx, cy, s, min_nz)`` (the right-hand side),
        ``pcg_begin()``, ``pcg_iteration()``, ``residual()``,
        ``finish(out, reference)``, ``load(depth)`` (warm start from a depth map),
        ``mg_step()`` (one multigrid correction), ``rhs_begin(...)`` (with ``pcg_begin``),
        ``scalars()`` (``sc`` as a vector), the builder ``frame(cycles)`` of
        the one-launch frame kernel (right-hand side, ``cycles`` corrections,
        depth), the builders ``persistent(nblocks, bd)`` (the whole frame in one
        persistent task, ``cycles`` a runtime argument) and ``hybrid(cycles, top,
        nblocks, bd)`` (levels ``top`` and below in one), and ``parts``: the
        namespace of fields, constants and ti.funcs the kernels are built from
        (``perf/_fused_variants.py`` builds the profiling kernels ``vcycle_only``,
        ``coarse_only``, ``noop`` from it).  ``F`` also holds
        ``bar`` (i32 (2,): barrier arrivals, timeout flag), ``geo`` (i32 (L, 3)),
        ``cmap`` (coarsest cell to its index in ``cidx``, -1) and ``fcv`` (the
        coarsest right-hand side, gathered) for them, and ``slot`` (f64 (2, NSLOT))
        and ``wcnt`` (i32 (1,)), zeroed: with them, on CUDA, the last z update of a
        one-component frame totals the finish's sums itself (``_warp_total``).
    """
    ns = _namespace(F, geo, npairs, omega, nc, perspective)
    for build in (reduce_funcs, level_funcs, vcycle_funcs, rhs_funcs, warp_funcs, update_funcs, finish_funcs,
                  frame_funcs):
        vars(ns).update(build(ns))
    K = {**cg_kernels(ns), **step_kernels(ns), "frame": ns.frame}
    K.update(persistent_builders(ns))
    K["parts"] = ns
    return K


def _namespace(F: dict, geo: list, npairs: int, omega: float, nc: int, perspective: bool) -> SimpleNamespace:
    """The fields of ``F`` and the constants of the geometry, by the names the kernels use (see :func:`make_fused`)."""
    L = len(geo)
    h0, w0 = geo[0][1], geo[0][2]
    wx, wy, dg, e, f, t = F["wx"], F["wy"], F["dg"], F["e"], F["f"], F["t"]
    z, b, r, p, q, sc = F["z"], F["b"], F["r"], F["p"], F["q"], F["sc"]
    pinv, cidx, lab, csum, cden, ccnt = F["pinv"], F["cidx"], F["lab"], F["csum"], F["cden"], F["ccnt"]
    ncomp = ccnt.shape[0]
    om = omega

    red, part, part2 = F["red"], F["part"], F["part2"]
    bar, geof, cmap, fcv = F["bar"], F["geo"], F["cmap"], F["fcv"]
    fold0 = npairs == 1 and L > 1  # level 0's last sweep computed by its consumer
    CH = 8  # rows per chunk of the two-stage reductions (8: ~H W / 8 threads in the first stage)
    NCH = (h0 + CH - 1) // CH
    NIT = NCH * w0  # (row chunk, column) items of the chunked passes
    cuda = ti.lang.impl.current_cfg().arch == ti.cuda
    slot, wcnt = F["slot"], F["wcnt"]
    # on CUDA, the last z update of a one-component frame also totals its sums: a warp
    # reduction, one atomic per warp into NSLOT slots, the last warp folds them (no task)
    wsums = cuda and ncomp == 1
    NSLOT = slot.shape[1]
    NPAD = (NIT + 31) // 32 * 32  # whole warps
    NW = NPAD // 32
    return SimpleNamespace(
        wx=wx, wy=wy, dg=dg, e=e, f=f, t=t, z=z, b=b, r=r, p=p, q=q, sc=sc, pinv=pinv, cidx=cidx, lab=lab,
        csum=csum, cden=cden, ccnt=ccnt, red=red, part=part, part2=part2, bar=bar, geof=geof, cmap=cmap, fcv=fcv,
        slot=slot, wcnt=wcnt, geo=geo, L=L, h0=h0, w0=w0, npairs=npairs, om=om, nc=nc, perspective=perspective,
        ncomp=ncomp, fold0=fold0, CH=CH, NCH=NCH, NIT=NIT, cuda=cuda, wsums=wsums, NSLOT=NSLOT, NPAD=NPAD, NW=NW)


def rhs_funcs(ns) -> dict:
    """The right-hand side from the normals and the level-0 residual.

    Args:
        ns: the namespace of :func:`make_fused` (fields ``wx, wy, dg, b, f, z, red``; ``h0``, ``w0``,
            ``perspective``; ``reduce_into``).

    Returns:
        dict of ti.funcs ``_rhs``, ``_steps``, ``_rhs_at``, ``_res0``.
    """
    wx, wy, dg, b, f, z, red = ns.wx, ns.wy, ns.dg, ns.b, ns.f, ns.z, ns.red
    h0, w0, perspective, reduce_into = ns.h0, ns.w0, ns.perspective, ns.reduce_into

    @ti.func
    def _rhs(nrm: ti.template(), fx: ti.template(), fy: ti.template(), cx: ti.template(), cy: ti.template(),
             s: ti.template(), min_nz: ti.template(), norm: ti.template(), res: ti.template()):
        """b = -div of the mean steps of u (:func:`gpps.kernels.poisson.pixel_steps`,
        uniform weights), in one pass over the normals (``_rhs_at``); with
        ``norm``, sc[7] = |b|^2; with ``res``, also f = b - A z (the first
        correction's residual, in the same pass).  The scalars are template
        parameters: passed by value, Taichi would copy them into locals in a
        serial task of their own (a launch)."""
        for i, j in ti.ndrange(h0, w0):
            _rhs_at(nrm, i, j, fx, fy, cx, cy, s, min_nz, norm, res)
        if ti.static(norm):
            reduce_into(7)  # |b|^2

    @ti.func
    def _steps(nrm: ti.template(), i, j, fx: ti.template(), fy: ti.template(), cx: ti.template(),
               cy: ti.template(), s: ti.template(), min_nz: ti.template()):
        """The steps of u along j and i at pixel (i, j) in the field precision (0 outside the mask)."""
        a = ti.cast(0, ti.f64)
        c = ti.cast(0, ti.f64)
        if dg[i, j] > 0:
            a, c = pixel_steps(nrm, i, j, ti.static(perspective), fx, fy, cx, cy, s, min_nz)
        return ti.cast(a, b.dtype), ti.cast(c, b.dtype)

    @ti.func
    def _rhs_at(nrm: ti.template(), i, j, fx: ti.template(), fy: ti.template(), cx: ti.template(),
                cy: ti.template(), s: ti.template(), min_nz: ti.template(), norm: ti.template(), res: ti.template()):
        """b[i, j] = :func:`gpps.kernels.poisson.div_mean_steps` of the steps, those of the pixel
        and its four neighbours computed here from the normals (cached reads; a steps pass
        would write and read 8 bytes a pixel more and cost a task); ``norm``: red = b^2;
        ``res``: f = b - A z (the value of b just written by this thread)."""
        a0, c0 = _steps(nrm, i, j, fx, fy, cx, cy, s, min_nz)
        v = a0 * 0
        if j > 0:
            al, _cl = _steps(nrm, i, j - 1, fx, fy, cx, cy, s, min_nz)
            v += wx[i, j - 1] * 0.5 * (al + a0)
        if j < w0 - 1:
            ar, _cr = _steps(nrm, i, j + 1, fx, fy, cx, cy, s, min_nz)
            v -= wx[i, j] * 0.5 * (a0 + ar)
        if i > 0:
            _au, cu = _steps(nrm, i - 1, j, fx, fy, cx, cy, s, min_nz)
            v += wy[i - 1, j] * 0.5 * (cu + c0)
        if i < h0 - 1:
            _ad, cd = _steps(nrm, i + 1, j, fx, fy, cx, cy, s, min_nz)
            v -= wy[i, j] * 0.5 * (c0 + cd)
        b[i, j] = v
        if ti.static(norm):
            red[i, j] = ti.cast(_sq(v), red.dtype)
        if ti.static(res):
            f[i, j] = _res0(i, j)

    @ti.func
    def _res0(i, j):
        """The level-0 residual ``(b - A z)[i, j]`` (0 outside the mask)."""
        d = dg[i, j]
        v = b[i, j] * 0
        if d > 0:
            v = b[i, j] - d * z[i, j] + _neigh(z, wx, wy, i, j, 0, h0, w0)
        return v

    return {"_rhs": _rhs, "_steps": _steps, "_rhs_at": _rhs_at, "_res0": _res0}


def cg_kernels(ns) -> dict:
    """The multigrid-preconditioned conjugate gradient: its start and one iteration, each one launch.

    Args:
        ns: the namespace of :func:`make_fused`.

    Returns:
        dict of kernels ``pcg_begin``, ``rhs_begin``, ``pcg_iteration``.
    """
    wx, wy, dg, f, t, z, r, p, q, sc, part = ns.wx, ns.wy, ns.dg, ns.f, ns.t, ns.z, ns.r, ns.p, ns.q, ns.sc, ns.part
    h0, w0, CH, NCH = ns.h0, ns.w0, ns.CH, ns.NCH
    stage2, vcycle, _res0, _rhs = ns.stage2, ns.vcycle, ns._res0, ns._rhs

    @ti.func
    def _begin():
        """r = b - A z, f = r, t = M r, p = t, rz = r . t, rr = |r|^2 (reductions fused into the loops)."""
        sc[RR] = 0
        sc[RZ] = 0
        for c, j in ti.ndrange(NCH, w0):
            acc = ti.cast(0, ti.f64)
            for ii in range(CH):
                i = c * CH + ii
                if i < h0:
                    v = _res0(i, j)
                    r[i, j] = v
                    f[i, j] = v
                    acc += _sq(v)
            part[c, j] = acc
        stage2(RR)
        vcycle()
        for c, j in ti.ndrange(NCH, w0):
            acc = ti.cast(0, ti.f64)
            for ii in range(CH):
                i = c * CH + ii
                if i < h0:
                    p[i, j] = t[i, j]
                    acc += _mul(r[i, j], t[i, j])
            part[c, j] = acc
        stage2(RZ)

    @ti.kernel
    def pcg_begin():
        """Start the CG from the current z (see ``_begin``)."""
        _begin()

    @ti.kernel
    def rhs_begin(nrm: ti.types.ndarray(), fx: ti.f64, fy: ti.f64, cx: ti.f64, cy: ti.f64, s: ti.f64, min_nz: ti.f64):
        """``rhs_only`` and ``pcg_begin`` in one launch (the per-frame path)."""
        _rhs(nrm, fx, fy, cx, cy, s, min_nz, True, False)
        _begin()

    @ti.kernel
    def pcg_iteration():
        """One preconditioned CG iteration, V-cycle included (one launch, about 30 tasks)."""
        sc[PQ] = 0
        sc[RR] = 0
        sc[RZN] = 0
        for c, j in ti.ndrange(NCH, w0):
            acc = ti.cast(0, ti.f64)
            for ii in range(CH):
                i = c * CH + ii
                if i < h0:
                    d = dg[i, j]
                    v = p[i, j] * 0
                    if d > 0:
                        v = d * p[i, j] - _neigh(p, wx, wy, i, j, 0, h0, w0)
                    q[i, j] = v
                    acc += _mul(p[i, j], v)
            part[c, j] = acc
        stage2(PQ)
        sc[ALPHA] = 0
        if sc[PQ] > 0:
            sc[ALPHA] = sc[RZ] / sc[PQ]
        for c, j in ti.ndrange(NCH, w0):
            acc = ti.cast(0, ti.f64)
            a = ti.cast(sc[ALPHA], z.dtype)
            for ii in range(CH):
                i = c * CH + ii
                if i < h0:
                    z[i, j] += a * p[i, j]
                    rv = r[i, j] - a * q[i, j]
                    r[i, j] = rv
                    f[i, j] = rv
                    acc += _sq(rv)
            part[c, j] = acc
        stage2(RR)
        vcycle()
        for c, j in ti.ndrange(NCH, w0):
            acc = ti.cast(0, ti.f64)
            for ii in range(CH):
                i = c * CH + ii
                if i < h0:
                    acc += _mul(r[i, j], t[i, j])
            part[c, j] = acc
        stage2(RZN)
        beta = sc[RZN] * 0
        if sc[RZ] > 0:
            beta = sc[RZN] / sc[RZ]
        sc[RZ] = sc[RZN]
        sc[5] = beta
        for i, j in ti.ndrange(h0, w0):
            p[i, j] = t[i, j] + ti.cast(sc[5], p.dtype) * p[i, j]

    return {"pcg_begin": pcg_begin, "rhs_begin": rhs_begin, "pcg_iteration": pcg_iteration}


def step_kernels(ns) -> dict:
    """The kernels of the multigrid-correction path and the host's reads and writes.

    Args:
        ns: the namespace of :func:`make_fused`.

    Returns:
        dict of kernels ``mg_step``, ``rhs_only``, ``residual``, ``load``, ``finish``, ``scalars``.
    """
    z, sc, red, lab = ns.z, ns.sc, ns.red, ns.lab
    h0, w0, perspective = ns.h0, ns.w0, ns.perspective
    _correct, _rhs, _res0, reduce_into, _finish = ns._correct, ns._rhs, ns._res0, ns.reduce_into, ns._finish

    @ti.kernel
    def mg_step():
        """One multigrid correction ``z += M (b - A z)`` (a V-cycle from zero on the residual).

        The stationary iteration, not CG: one V-cycle and two level-0 passes per
        launch, for warm-started frames whose error is already small and smooth.
        No reduction: the ``tol`` mode reads the true residual (``residual``).
        """
        _correct(False, False)

    @ti.kernel
    def rhs_only(nrm: ti.types.ndarray(), fx: ti.f64, fy: ti.f64, cx: ti.f64, cy: ti.f64, s: ti.f64, min_nz: ti.f64):
        """b = -div of the steps from the normals (see ``_rhs``), |b|^2 in sc[7], without starting
        the CG (the multigrid-correction path)."""
        _rhs(nrm, fx, fy, cx, cy, s, min_nz, True, False)

    @ti.kernel
    def residual():
        """sc[RR] = |b - A z|^2 (the true residual, not the CG recurrence)."""
        for i, j in ti.ndrange(h0, w0):
            v = _res0(i, j)
            red[i, j] = ti.cast(_sq(v), red.dtype)
        reduce_into(RR)

    @ti.kernel
    def load(depth: ti.types.ndarray()):
        """z = u of a depth map (log-depth under perspective); 0 outside the mask or where depth <= 0."""
        for i, j in ti.ndrange(h0, w0):
            v = ti.cast(0, ti.f64)
            dd = ti.cast(depth[i, j], ti.f64)
            if lab[i, j] >= 0:
                if ti.static(perspective):
                    if dd > 0:
                        v = ti.log(dd)
                else:
                    v = dd
            z[i, j] = ti.cast(v, z.dtype)

    @ti.kernel
    def finish(out: ti.types.ndarray(), reference: ti.f64):
        """Fix each component's constant and write the depth (see ``_finish``)."""
        _finish(out, reference, False)

    @ti.kernel
    def scalars() -> ti.types.vector(8, ti.f64):
        """All of ``sc`` in one read (one launch and one copy instead of one per element)."""
        return ti.Vector([sc[0], sc[1], sc[2], sc[3], sc[4], sc[5], sc[6], sc[7]], ti.f64)

    return {"mg_step": mg_step, "rhs_only": rhs_only, "residual": residual, "load": load, "finish": finish,
            "scalars": scalars}


def frame_funcs(ns) -> dict:
    """The one-launch frame: right-hand side, V-cycle corrections, depth.

    Args:
        ns: the namespace of :func:`make_fused` (fields ``f``; ``h0``, ``w0``; ``_res0``,
            ``vcycle_levels``, ``_update_z``, ``_rhs``, ``_finish``).

    Returns:
        dict: the ti.func ``_correct``, the builder ``frame(cycles)`` and ``_frame_kernel(cycles,
        correct)`` (the frame around any correction: the hybrid frame's too).
    """
    f, h0, w0 = ns.f, ns.h0, ns.w0
    _res0, vcycle_levels, _update_z, _rhs, _finish = ns._res0, ns.vcycle_levels, ns._update_z, ns._rhs, ns._finish

    @ti.func
    def _correct(res_ready: ti.template(), last: ti.template()):
        """z += M (b - A z): one V-cycle correction, no reductions (``res_ready``: f
        already holds b - A z, written by ``_rhs``; ``last``: the frame's last, see
        ``_update_z``)."""
        if ti.static(not res_ready):
            for i, j in ti.ndrange(h0, w0):
                f[i, j] = _res0(i, j)
        vcycle_levels()
        _update_z(last)

    frames = {}

    def frame(cycles: int):
        """The whole per-frame integration as *one* launch: right-hand side,
        ``cycles`` V-cycle corrections from the current ``z`` (the previous
        frame's solution, or 0 after a reset) and the depth write
        (``frame(nrm, out, fx, fy, cx, cy, s, min_nz, reference)``).  One
        kernel per ``cycles``, built on first use."""
        if cycles not in frames:
            frames[cycles] = _frame_kernel(cycles, _correct)
        return frames[cycles]

    def _frame_kernel(cycles: int, correct):
        """The frame kernel around a correction ``correct(res_ready, last)`` (a ti.func)."""

        @ti.kernel
        def _frame(nrm: ti.types.ndarray(), out: ti.types.ndarray(), fx: ti.f64, fy: ti.f64, cx: ti.f64,
                   cy: ti.f64, s: ti.f64, min_nz: ti.f64, reference: ti.f64):
            _rhs(nrm, fx, fy, cx, cy, s, min_nz, False, cycles > 0)
            for cyc in ti.static(range(cycles)):
                correct(cyc == 0, cyc == cycles - 1)
            _finish(out, reference, cycles > 0)

        return _frame

    return {"_correct": _correct, "frame": frame, "_frame_kernel": _frame_kernel}

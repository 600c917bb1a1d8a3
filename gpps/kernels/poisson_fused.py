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
software grid barriers (``persistent``, ``hybrid`` below; about 2 us a
barrier on an H100, ``perf/taichi_grid_barrier.py``).

:func:`make_fused` builds the kernels for one set of fields and one geometry;
the fields are closed over (not passed), so each instance of
:class:`gpps.pipeline.integration_device.StreamIntegrator` compiles its own.
Only device code lives here.
"""

from gpps._taichi import ti
from gpps.kernels.poisson import ALPHA, PQ, RR, RZ, RZN, _jacobi_point, _mul, _neigh, _sq, pixel_steps


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
        nblocks, bd)`` (levels ``top`` and below in one), and for profiling
        ``vcycle_only()``, ``coarse_only()``, ``noop()``.  ``F`` also holds
        ``bar`` (i32 (2,): barrier arrivals, timeout flag), ``geo`` (i32 (L, 3)),
        ``cmap`` (coarsest cell to its index in ``cidx``, -1) and ``fcv`` (the
        coarsest right-hand side, gathered) for them, and ``slot`` (f64 (2, NSLOT))
        and ``wcnt`` (i32 (1,)), zeroed: with them, on CUDA, the last z update of a
        one-component frame totals the finish's sums itself (``_warp_total``).
    """
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

    @ti.func
    def stage2(idx: ti.template()):
        """sc[idx] += the column sums of ``part`` (sc[idx] zeroed beforehand)."""
        for j in range(w0):
            s = ti.cast(0, ti.f64)
            for c in range(NCH):
                s += part[c, j]
            sc[idx] += s

    @ti.func
    def reduce_into(idx: ti.template()):
        """sc[idx] = sum of ``red`` over level 0, in float64, without same-address atomics per pixel.

        Stage 1: one thread per (row chunk, column) sums CH rows (coalesced);
        stage 2 (:func:`stage2`): one thread per column sums the chunks and adds
        to sc[idx] (W atomics instead of H * W, which serialised at ~1.4 ns each
        on an H100).
        """
        for c, j in ti.ndrange(NCH, w0):
            s = ti.cast(0, ti.f64)
            for ii in range(CH):
                i = c * CH + ii
                if i < h0:
                    s += ti.cast(red[i, j], ti.f64)
            part[c, j] = s
        sc[idx] = 0
        stage2(idx)

    @ti.func
    def comp_sums(dst: ti.template()):
        """dst[c] = sum of ``red`` over mask component c (labels ``lab``, -1 outside).

        One component: :func:`reduce_into`.  Several: per (row chunk, column)
        partial sums with one atomic per run of equal labels.
        """
        if ti.static(ncomp == 1):
            reduce_into(6)
            dst[0] = sc[6]
        else:
            for c in range(ncomp):
                dst[c] = 0
            for ch, j in ti.ndrange(NCH, w0):
                cur = -1
                s = ti.cast(0, ti.f64)
                for ii in range(CH):
                    i = ch * CH + ii
                    if i < h0:
                        c = lab[i, j]
                        if c != cur:
                            if cur >= 0:
                                dst[cur] += s
                            cur = c
                            s = 0.0
                        if c >= 0:
                            s += ti.cast(red[i, j], ti.f64)
                if cur >= 0:
                    dst[cur] += s

    @ti.func
    def _pre(i, j, off, h, w):
        """Two damped Jacobi sweeps from e = 0 in one pass: the first iterate
        ``e1 = omega f / d`` is pointwise, so the second reads it on the fly."""
        d = dg[i, off + j]
        v = f[i, off + j] * 0
        if d > 0:
            nb = f[i, off + j] * 0
            if j > 0:
                if dg[i, off + j - 1] > 0:
                    nb += wx[i, off + j - 1] * om * f[i, off + j - 1] / dg[i, off + j - 1]
            if j < w - 1:
                if dg[i, off + j + 1] > 0:
                    nb += wx[i, off + j] * om * f[i, off + j + 1] / dg[i, off + j + 1]
            if i > 0:
                if dg[i - 1, off + j] > 0:
                    nb += wy[i - 1, off + j] * om * f[i - 1, off + j] / dg[i - 1, off + j]
            if i < h - 1:
                if dg[i + 1, off + j] > 0:
                    nb += wy[i, off + j] * om * f[i + 1, off + j] / dg[i + 1, off + j]
            e1 = om * f[i, off + j] / d
            v = (1 - om) * e1 + om * (f[i, off + j] + nb) / d
        return v

    @ti.func
    def _corr(i, j, off, offc):
        """The level's iterate (in t) plus the prolonged (injected) coarse correction (in t, coarse level)."""
        v = t[i, off + j] * 0
        if dg[i, off + j] > 0:
            v = t[i, off + j] + t[i // 2, offc + j // 2]
        return v

    @ti.func
    def _post_first(i, j, off, h, w, offc):
        """One damped Jacobi sweep applied to (iterate + coarse correction), computed on the fly."""
        d = dg[i, off + j]
        v = f[i, off + j] * 0
        if d > 0:
            nb = f[i, off + j] * 0
            if j > 0:
                nb += wx[i, off + j - 1] * _corr(i, j - 1, off, offc)
            if j < w - 1:
                nb += wx[i, off + j] * _corr(i, j + 1, off, offc)
            if i > 0:
                nb += wy[i - 1, off + j] * _corr(i - 1, j, off, offc)
            if i < h - 1:
                nb += wy[i, off + j] * _corr(i + 1, j, off, offc)
            v = (1 - om) * _corr(i, j, off, offc) + om * (f[i, off + j] + nb) / d
        return v

    @ti.func
    def _res(i, j, off, h, w):
        """Residual f - A t at a fine point (0 outside the mask or the level)."""
        rr = f[i, off + j] * 0
        if i < h and j < w:
            d = dg[i, off + j]
            if d > 0:
                rr = f[i, off + j] - d * t[i, off + j] + _neigh(t, wx, wy, i, j, off, h, w)
        return rr

    @ti.func
    def _restrict_at(ci, cj, off, h, w, offc, last):
        """f at coarse cell (ci, cj) = the sum of the fine 2x2 block's residuals; into the
        coarsest level (``last``) also gathered into ``fcv`` (its active cells in order)."""
        v = (_res(2 * ci, 2 * cj, off, h, w) + _res(2 * ci, 2 * cj + 1, off, h, w)
             + _res(2 * ci + 1, 2 * cj, off, h, w) + _res(2 * ci + 1, 2 * cj + 1, off, h, w))
        f[ci, offc + cj] = v
        if last:
            m = cmap[ci, cj]
            if m >= 0:
                fcv[m] = v

    @ti.func
    def _coarse_at(kk):
        """t = (pinv f)[kk] at the coarsest level's active cell ``kk`` (f gathered in ``fcv``).

        ``pinv`` is symmetric (the pseudo-inverse of a symmetric matrix), so
        thread ``kk`` reads column ``kk``: neighbouring threads read
        neighbouring addresses (coalesced) instead of rows ``nc`` apart; every
        thread reads the same ``fcv[m]`` (one broadcast, no index lookups).
        """
        acc = fcv[0] * 0
        for m in range(nc):
            acc += pinv[m, kk] * fcv[m]
        t[cidx[kk, 0], cidx[kk, 1]] = acc

    @ti.func
    def coarse_solve():
        """t = pinv f on the coarsest level's active cells (one thread per cell)."""
        for kk in range(nc):
            _coarse_at(kk)

    @ti.func
    def vcycle_levels():
        """One V-cycle from zero on level 0's f, every level unrolled, except (with ``npairs == 1``)
        level 0's last sweep: its consumer computes it (``_mf0``) in the pass that uses it (the depth
        update, or the copy into t), one level-0 pass fewer.

        Per level on the way down, two tasks: the pre-smoothing pair (from zero,
        fused) and residual + restriction (fused); on the way up two: the first
        post-smoothing sweep with the coarse correction added on the fly, and the
        second.  Each level's iterate ends in ``t``.  Same operator as
        :func:`gpps.kernels.poisson.down` / ``up`` (2x2 aggregation, injection,
        damped Jacobi), with ``npairs - 1`` further plain sweep pairs.
        """
        vdown(L - 1)
        coarse_solve()
        vup(L - 1)

    @ti.func
    def vdown(top: ti.template()):
        """The descent of ``vcycle_levels`` on levels ``0 .. top - 1`` (two tasks each): f restricted to level ``top``.
        Below the coarsest (``top < L - 1``) the restriction into level ``top`` also zeroes the grid-barrier
        counter of the persistent task that takes over there."""
        for k in ti.static(range(top)):
            off, h, w = ti.static(geo[k])
            offc, hc, wc = ti.static(geo[k + 1])
            for i, j in ti.ndrange(h, w):
                t[i, off + j] = _pre(i, j, off, h, w)
            for _ in ti.static(range(npairs - 1)):
                for i, j in ti.ndrange(h, w):
                    e[i, off + j] = _jacobi_point(t, f, wx, wy, dg, i, j, off, h, w, om)
                for i, j in ti.ndrange(h, w):
                    t[i, off + j] = _jacobi_point(e, f, wx, wy, dg, i, j, off, h, w, om)
            for ci, cj in ti.ndrange(hc, wc):
                _restrict_at(ci, cj, off, h, w, offc, ti.static(k == L - 2))
                if ti.static(k == top - 1 and top < L - 1):
                    if ci == 0 and cj == 0:
                        bar[0] = 0

    @ti.func
    def vup(top: ti.template()):
        """The ascent of ``vcycle_levels`` on levels ``top - 1 .. 0`` (level ``top``'s iterate in t)."""
        for k in ti.static(range(top - 1, -1, -1)):
            off, h, w = ti.static(geo[k])
            offc = ti.static(geo[k + 1][0])
            for i, j in ti.ndrange(h, w):
                e[i, off + j] = _post_first(i, j, off, h, w, offc)
            if ti.static(k > 0 or not fold0):
                for i, j in ti.ndrange(h, w):
                    t[i, off + j] = _jacobi_point(e, f, wx, wy, dg, i, j, off, h, w, om)
                for _ in ti.static(range(npairs - 1)):
                    for i, j in ti.ndrange(h, w):
                        e[i, off + j] = _jacobi_point(t, f, wx, wy, dg, i, j, off, h, w, om)
                    for i, j in ti.ndrange(h, w):
                        t[i, off + j] = _jacobi_point(e, f, wx, wy, dg, i, j, off, h, w, om)

    @ti.func
    def _mf0(i, j):
        """``(M f_0)[i, j]``: level 0's result of the V-cycle run by ``vcycle_levels``."""
        v = t[0, 0] * 0
        if ti.static(fold0):
            v = _jacobi_point(e, f, wx, wy, dg, i, j, 0, h0, w0, om)
        else:
            v = t[i, j]
        return v

    @ti.func
    def vcycle():
        """t_0 = M f_0 (one V-cycle from zero on level 0's f)."""
        vcycle_levels()
        if ti.static(fold0):
            for i, j in ti.ndrange(h0, w0):
                t[i, j] = _mf0(i, j)

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
    def vcycle_only():
        """One V-cycle on the current level-0 ``f`` (profiling)."""
        vcycle()

    @ti.kernel
    def coarse_only():
        """The coarsest-level solve alone (profiling)."""
        coarse_solve()

    @ti.kernel
    def noop():
        """One empty task (profiling: the launch overhead)."""
        for i in range(1):
            sc[6] += 0

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

    @ti.func
    def _chunk_sums(c, j, update: ti.template()):
        """part[c, j], part2[c, j] = the sums of u and exp(u) over rows ``c * CH ..`` of
        column j inside the mask, u = z (``update``: u = z + M f_0, written back); the
        thread of (0, 0) zeroes sc[8], sc[9] for the column totals of the next task."""
        if c == 0 and j == 0:
            sc[8] = 0
            sc[9] = 0
        a, x = _chunk_acc(c, j, update)
        part[c, j] = a
        part2[c, j] = x

    @ti.func
    def _shfl64(v, k):
        """``v`` of the lane ``k`` above (CUDA warp shuffle), moved exactly as two 32-bit halves
        (Taichi 1.7's f32 shuffle result cannot be cast to f64: its LLVM cast asserts)."""
        bits = ti.bit_cast(v, ti.i64)
        hi = ti.simt.warp.shfl_down_i32(ti.u32(0xFFFFFFFF), ti.cast(bits >> 32, ti.i32), k)
        lo = ti.simt.warp.shfl_down_i32(ti.u32(0xFFFFFFFF), ti.cast(bits & ti.i64(0xFFFFFFFF), ti.i32), k)
        return ti.bit_cast((ti.cast(hi, ti.i64) << 32) | (ti.cast(lo, ti.i64) & ti.i64(0xFFFFFFFF)), ti.f64)

    @ti.func
    def _wsum(v):
        """The f64 sum of ``v`` over the warp, in lane 0 (a shuffle-down tree)."""
        acc = ti.cast(v, ti.f64)
        for k in ti.static([16, 8, 4, 2, 1]):
            acc += _shfl64(acc, k)
        return acc

    @ti.func
    def _warp_total(it, a, x):
        """sc[8], sc[9] = the totals of ``a`` and ``x`` over the items ``it < NPAD`` of this task
        (CUDA, every lane of every warp calls it once per item): a warp sum, one atomic per warp
        into slot ``warp % NSLOT``; the warp that arrives last (counted in ``wcnt``) folds the slots
        into sc and zeroes the slots and the count for the next frame."""
        ta = _wsum(a)
        tx = ta * 0
        if ti.static(perspective):
            tx = _wsum(x)
        if it % 32 == 0:
            sl = (it // 32) % NSLOT
            ti.atomic_add(slot[0, sl], ta)
            if ti.static(perspective):
                ti.atomic_add(slot[1, sl], tx)
            ti.simt.grid.memfence()
            if ti.atomic_add(wcnt[0], 1) == NW - 1:
                ti.simt.grid.memfence()
                sa = ti.cast(0, ti.f64)
                sx = ti.cast(0, ti.f64)
                for k in range(NSLOT):
                    sa += ti.atomic_add(slot[0, k], 0.0)
                    sx += ti.atomic_add(slot[1, k], 0.0)
                    slot[0, k] = 0
                    slot[1, k] = 0
                sc[8] = sa
                sc[9] = sx
                wcnt[0] = 0

    @ti.func
    def _chunk_acc(c, j, update: ti.template()):
        """(sum u, sum exp(u)) over rows ``c * CH ..`` of column j inside the mask, u = z
        (``update``: u = z + M f_0, written back)."""
        a = ti.cast(0, ti.f64)
        x = ti.cast(0, ti.f64)
        for ii in range(CH):
            i = c * CH + ii
            if i < h0:
                u = z[i, j]
                if ti.static(update):
                    u += _mf0(i, j)
                    z[i, j] = u
                if lab[i, j] >= 0:
                    a += ti.cast(u, ti.f64)
                    if ti.static(perspective):
                        x += ti.exp(ti.cast(u, ti.f64))
        return a, x

    @ti.func
    def _finish1(out: ti.template(), reference: ti.template(), summed: ti.template()):
        """``_finish`` for one component in three tasks: the sums of u and exp(u) in one
        pass (sc[8], sc[9]; exp(u - m) sums to exp(-m) sum exp(u), so the perspective
        scale needs no second pass over the centred u), their column totals, the write.
        ``summed``: the first pass was done by the last z update (``_update_z``)."""
        if ti.static(not summed):
            for c, j in ti.ndrange(NCH, w0):
                _chunk_sums(c, j, False)
        if ti.static(not (summed and wsums)):
            for j in range(w0):
                a = ti.cast(0, ti.f64)
                x = ti.cast(0, ti.f64)
                for c in range(NCH):
                    a += part[c, j]
                    x += part2[c, j]
                sc[8] += a
                sc[9] += x
        for i, j in ti.ndrange(h0, w0):
            v = ti.cast(0, ti.f64)
            if lab[i, j] >= 0:
                m = sc[8] / ccnt[0]
                u = ti.cast(z[i, j], ti.f64) - m
                z[i, j] = ti.cast(u, z.dtype)
                if ti.static(perspective):
                    v = ti.exp(u)
                    if reference > 0:
                        v *= reference * ccnt[0] / (sc[9] * ti.exp(-m))
                else:
                    v = u + ti.max(reference, 0.0)
            out[i, j] = ti.cast(v, ti.f32)

    @ti.func
    def _finish(out: ti.template(), reference: ti.template(), summed: ti.template()):
        """Fix each component's constant and write the depth.

        u's mean is set to 0 per component; orthographic depth = u + reference,
        perspective depth = exp(u) scaled so that each component's mean depth
        is ``reference`` (``reference <= 0``: left at exp(u), mean log-depth 0).
        z keeps the centred u (the next frame's warm start).  ``summed``: the
        last z update left the one-component sums in ``part``/``part2``.
        """
        if ti.static(ncomp == 1):
            _finish1(out, reference, summed)
        else:
            _finish_components(out, reference)

    @ti.func
    def _finish_components(out: ti.template(), reference: ti.template()):
        """``_finish`` for any number of components (per-component sums, two passes)."""
        for i, j in ti.ndrange(h0, w0):
            red[i, j] = ti.select(lab[i, j] >= 0, z[i, j], 0.0)
        comp_sums(csum)
        for i, j in ti.ndrange(h0, w0):
            c = lab[i, j]
            v = ti.cast(0, red.dtype)
            if c >= 0:
                u = ti.cast(z[i, j], ti.f64) - csum[c] / ccnt[c]
                z[i, j] = ti.cast(u, z.dtype)
                if ti.static(perspective):
                    v = ti.cast(ti.exp(u), red.dtype)
            red[i, j] = v
        if ti.static(perspective):
            comp_sums(cden)
        for i, j in ti.ndrange(h0, w0):
            c = lab[i, j]
            v = ti.cast(0, ti.f64)
            if c >= 0:
                u = ti.cast(z[i, j], ti.f64)
                if ti.static(perspective):
                    v = ti.exp(u)
                    if reference > 0:
                        v *= reference * ccnt[c] / cden[c]
                else:
                    v = u + ti.max(reference, 0.0)
            out[i, j] = ti.cast(v, ti.f32)

    @ti.kernel
    def finish(out: ti.types.ndarray(), reference: ti.f64):
        """Fix each component's constant and write the depth (see ``_finish``)."""
        _finish(out, reference, False)

    @ti.func
    def _update_z(sums: ti.template()):
        """z += M f_0 (level 0's V-cycle result, ``_mf0``).  With ``sums`` and one
        component, per (row chunk, column) as in ``_finish1``'s first pass, whose
        sums of the new u and exp(u) it leaves in ``part``/``part2`` (one level-0
        pass and one task fewer; ``_mf0`` reads no z, so the update is in place).
        On CUDA it also totals them into sc[8], sc[9] (``_warp_total``: a warp
        reduction and a slot atomic per warp), and the finish skips its column-totals
        task."""
        if ti.static(sums and wsums):
            ti.loop_config(block_dim=256)
            for it in range(NPAD):
                a = ti.cast(0, ti.f64)
                x = ti.cast(0, ti.f64)
                if it < NIT:
                    a, x = _chunk_acc(it // w0, it % w0, True)
                _warp_total(it, a, x)
        elif ti.static(sums and ncomp == 1):
            for c, j in ti.ndrange(NCH, w0):
                _chunk_sums(c, j, True)
        else:
            for i, j in ti.ndrange(h0, w0):
                z[i, j] += _mf0(i, j)

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

    pframes = {}
    LIMIT = 1 << 20  # polls before a grid barrier gives up (a block that never became resident)

    def _grid_parts(nblocks: int, bd: int):
        """The grid barrier and the persistent levels for ``nblocks x bd`` threads (see :func:`persistent`)."""
        if not cuda and nblocks * bd != 1:
            raise ValueError(f"nblocks, bd: off CUDA the persistent kernel runs as one thread (1, 1), got ({nblocks}, {bd})")
        NT = nblocks * bd

        @ti.func
        def gsync(tid, gen):
            """Grid barrier number ``gen`` of this task (``bar[0]`` zeroed before it); returns ``gen + 1``."""
            if ti.static(cuda):
                ti.simt.grid.memfence()
                ti.simt.block.sync()
            if tid % bd == 0:
                ti.atomic_add(bar[0], 1)
                target = gen * nblocks
                k = 0
                while True:
                    if ti.atomic_or(bar[0], 0) >= target:
                        break
                    k += 1
                    if k >= LIMIT:
                        ti.atomic_or(bar[1], 1)
                    if k % 1024 == 0:
                        if ti.atomic_or(bar[1], 0) != 0:
                            break
            if ti.static(cuda):
                ti.simt.block.sync()
                ti.simt.grid.memfence()
            return gen + 1

        @ti.func
        def sweep(tid, gen, src: ti.template(), dst: ti.template(), off, h, w):
            """One damped Jacobi sweep src -> dst on a level (cells strided over the threads), then a barrier."""
            n = h * w
            for kk in range((n + NT - 1) // NT):
                cc = tid + kk * NT
                if cc < n:
                    dst[cc // w, off + cc % w] = _jacobi_point(src, f, wx, wy, dg, cc // w, cc % w, off, h, w, om)
            return gsync(tid, gen)

        @ti.func
        def pairs(tid, gen, off, h, w):
            """The ``npairs - 1`` further sweep pairs t -> e -> t of a level."""
            g = gen
            for _ in ti.static(range(npairs - 1)):
                g = sweep(tid, g, t, e, off, h, w)
                g = sweep(tid, g, e, t, off, h, w)
            return g

        @ti.func
        def plevels(tid, gen, top: ti.template()):
            """The V-cycle from level ``top`` down (its f restricted already) and back up to level
            ``top``, a phase per grid barrier: t on level ``top`` = its V-cycle result (level 0's
            last sweep left to ``_mf0`` when ``top == 0``).  Returns the next barrier number."""
            g = gen
            # descent: pre-smoothing pair from zero, residual restricted to the next level
            for k in range(top, L - 1):
                off, h, w = geof[k, 0], geof[k, 1], geof[k, 2]
                n = h * w
                for kk in range((n + NT - 1) // NT):
                    cc = tid + kk * NT
                    if cc < n:
                        t[cc // w, off + cc % w] = _pre(cc // w, cc % w, off, h, w)
                g = gsync(tid, g)
                g = pairs(tid, g, off, h, w)
                offc, wc = geof[k + 1, 0], geof[k + 1, 2]
                ncl = geof[k + 1, 1] * wc
                for kk in range((ncl + NT - 1) // NT):
                    cc = tid + kk * NT
                    if cc < ncl:
                        _restrict_at(cc // wc, cc % wc, off, h, w, offc, k == L - 2)
                g = gsync(tid, g)
            # coarsest level: t = pinv f (f gathered into fcv by the last restriction)
            for kk in range((nc + NT - 1) // NT):
                cc = tid + kk * NT
                if cc < nc:
                    _coarse_at(cc)
            g = gsync(tid, g)
            # ascent: first sweep on (iterate + prolonged correction), then the second
            for kq in range(L - 1 - top):
                k = L - 2 - kq
                off, h, w = geof[k, 0], geof[k, 1], geof[k, 2]
                offc = geof[k + 1, 0]
                n = h * w
                for kk in range((n + NT - 1) // NT):
                    cc = tid + kk * NT
                    if cc < n:
                        e[cc // w, off + cc % w] = _post_first(cc // w, cc % w, off, h, w, offc)
                g = gsync(tid, g)
                second = 1  # level 0's second sweep is folded into the z update (_mf0)
                if ti.static(fold0 and top == 0):
                    second = ti.select(k > 0, 1, 0)
                if second:
                    g = sweep(tid, g, e, t, off, h, w)
                    g = pairs(tid, g, off, h, w)
            return g

        return NT, gsync, plevels

    def persistent(nblocks: int, bd: int):
        """The per-frame integration as *one* CUDA task of ``nblocks x bd`` threads whose
        phases are separated by software grid barriers (the frame of :func:`frame`,
        same arithmetic, without ~30 task launches: each costs the device about 3 us and
        the host about 5 us, a barrier about 2 us).

        ``persistent(nblocks, bd)(nrm, out, fx, fy, cx, cy, s, min_nz, reference, cycles)``
        runs the right-hand side, ``cycles >= 1`` V-cycle corrections and the depth write.
        The levels are a dynamic loop over the geometry field ``geo`` (one copy of each
        stencil in the code: it compiles in seconds); each phase visits its cells with a
        stride of ``nblocks * bd`` (neighbouring threads, neighbouring pixels).

        The barrier needs every block resident at once: ``nblocks`` must not exceed what the
        GPU holds (SMs times the blocks per SM that the kernel's registers allow).  A block
        that waits more than ``LIMIT`` polls sets ``bar[1]`` and lets the frame finish with
        wrong values instead of hanging; :class:`StreamIntegrator` checks the flag on its
        first frame and falls back to fewer blocks, then to :func:`frame`.  On the CPU
        (whose thread pool gives no such residency) it runs only as one thread,
        ``persistent(1, 1)``: every phase in order, which tests its arithmetic.
        """
        key = (nblocks, bd)
        if key in pframes:
            return pframes[key]
        NT, gsync, plevels = _grid_parts(nblocks, bd)
        n0 = h0 * w0

        @ti.kernel
        def _pframe(nrm: ti.types.ndarray(), out: ti.types.ndarray(), fx: ti.f64, fy: ti.f64, cx: ti.f64,
                    cy: ti.f64, s: ti.f64, min_nz: ti.f64, reference: ti.f64, cycles: ti.i32):
            bar[0] = 0
            ti.loop_config(block_dim=bd)
            for tid in range(NT):
                gen = 1
                # zero the per-component sums of the finish
                for kk in range((ncomp + NT - 1) // NT):
                    c = tid + kk * NT
                    if c < ncomp:
                        csum[c] = 0
                        cden[c] = 0
                # b = -div of the mean steps; f = b - A z (the first correction's residual)
                for kk in range((n0 + NT - 1) // NT):
                    cc = tid + kk * NT
                    if cc < n0:
                        _rhs_at(nrm, cc // w0, cc % w0, fx, fy, cx, cy, s, min_nz, False, True)
                gen = gsync(tid, gen)
                for cyc in range(cycles):
                    if cyc > 0:
                        for kk in range((n0 + NT - 1) // NT):
                            cc = tid + kk * NT
                            if cc < n0:
                                f[cc // w0, cc % w0] = _res0(cc // w0, cc % w0)
                        gen = gsync(tid, gen)
                    gen = plevels(tid, gen, 0)
                    # z += M f, per (row chunk, column); the last cycle also sums u and exp(u)
                    last = cyc == cycles - 1
                    for kk in range((NIT + NT - 1) // NT):
                        it = tid + kk * NT
                        if it < NIT:
                            ch = it // w0
                            j = it % w0
                            a = ti.cast(0, ti.f64)
                            x = ti.cast(0, ti.f64)
                            cur = -1
                            for ii in range(CH):
                                i = ch * CH + ii
                                if i < h0:
                                    u = z[i, j] + _mf0(i, j)
                                    z[i, j] = u
                                    if last:
                                        lc = lab[i, j]
                                        if ti.static(ncomp == 1):
                                            if lc >= 0:
                                                a += ti.cast(u, ti.f64)
                                                if ti.static(perspective):
                                                    x += ti.exp(ti.cast(u, ti.f64))
                                        else:
                                            if lc != cur:
                                                if cur >= 0:
                                                    ti.atomic_add(csum[cur], a)
                                                    ti.atomic_add(cden[cur], x)
                                                cur = lc
                                                a = 0.0
                                                x = 0.0
                                            if lc >= 0:
                                                a += ti.cast(u, ti.f64)
                                                if ti.static(perspective):
                                                    x += ti.exp(ti.cast(u, ti.f64))
                            if last:
                                if ti.static(ncomp == 1):
                                    part[ch, j] = a
                                    part2[ch, j] = x
                                else:
                                    if cur >= 0:
                                        ti.atomic_add(csum[cur], a)
                                        ti.atomic_add(cden[cur], x)
                    gen = gsync(tid, gen)
                if ti.static(ncomp == 1):
                    for kk in range((w0 + NT - 1) // NT):
                        j = tid + kk * NT
                        if j < w0:
                            a = ti.cast(0, ti.f64)
                            x = ti.cast(0, ti.f64)
                            for ch in range(NCH):
                                a += part[ch, j]
                                x += part2[ch, j]
                            ti.atomic_add(csum[0], a)
                            ti.atomic_add(cden[0], x)
                    gen = gsync(tid, gen)
                # centre u per component (the next frame's warm start) and write the depth
                for kk in range((n0 + NT - 1) // NT):
                    cc = tid + kk * NT
                    if cc < n0:
                        i = cc // w0
                        j = cc % w0
                        lc = lab[i, j]
                        v = ti.cast(0, ti.f64)
                        if lc >= 0:
                            m = csum[lc] / ccnt[lc]
                            u = ti.cast(z[i, j], ti.f64) - m
                            z[i, j] = ti.cast(u, z.dtype)
                            if ti.static(perspective):
                                v = ti.exp(u)
                                if reference > 0:
                                    v *= reference * ccnt[lc] / (cden[lc] * ti.exp(-m))
                            else:
                                v = u + ti.max(reference, 0.0)
                        out[i, j] = ti.cast(v, ti.f32)

        pframes[key] = _pframe
        return _pframe

    def hybrid(cycles: int, top: int, nblocks: int, bd: int):
        """:func:`frame` with the small levels in one persistent task.

        Levels ``0 .. top - 1`` (the large ones, memory-bound) run as in :func:`frame`, a
        task per phase at full occupancy; levels ``top`` and below (launch-bound: a few
        thousand cells or less, about 3 us of device time and 5 us of host time per task)
        run as one task of ``nblocks x bd`` threads with a grid barrier between phases
        (:func:`persistent`; the restriction into level ``top`` zeroes the barrier counter).
        ``1 <= top <= L - 2``.  Same call as :func:`frame`; one kernel per argument set.
        """
        if not 1 <= top <= L - 2:
            raise ValueError(f"top: expected 1 <= top <= {L - 2} (levels {L}), got {top}")
        key = ("hybrid", cycles, top, nblocks, bd)
        if key in pframes:
            return pframes[key]
        NT, gsync, plevels = _grid_parts(nblocks, bd)

        @ti.func
        def _hcorrect(res_ready: ti.template(), last: ti.template()):
            """``_correct`` with levels ``top`` and below in the persistent task."""
            if ti.static(not res_ready):
                for i, j in ti.ndrange(h0, w0):
                    f[i, j] = _res0(i, j)
            vdown(top)
            ti.loop_config(block_dim=bd)
            for tid in range(NT):
                plevels(tid, 1, top)
            vup(top)
            _update_z(last)

        pframes[key] = _frame_kernel(cycles, _hcorrect)
        return pframes[key]

    @ti.kernel
    def scalars() -> ti.types.vector(8, ti.f64):
        """All of ``sc`` in one read (one launch and one copy instead of one per element)."""
        return ti.Vector([sc[0], sc[1], sc[2], sc[3], sc[4], sc[5], sc[6], sc[7]], ti.f64)

    return {"pcg_begin": pcg_begin, "rhs_begin": rhs_begin, "pcg_iteration": pcg_iteration, "residual": residual,
            "finish": finish, "load": load, "mg_step": mg_step, "rhs_only": rhs_only, "vcycle_only": vcycle_only,
            "coarse_only": coarse_only, "noop": noop, "scalars": scalars, "frame": frame,
            "persistent": persistent, "hybrid": hybrid}

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

:func:`make_fused` builds the kernels for one set of fields and one geometry;
the fields are closed over (not passed), so each instance of
:class:`gpps.pipeline.integration_device.StreamIntegrator` compiles its own.
Only device code lives here.
"""

from gpps._taichi import ti
from gpps.kernels.poisson import ALPHA, PQ, RR, RZ, RZN, _jacobi_point, _mul, _neigh, _sq, div_mean_steps, pixel_steps


def make_fused(F: dict, geo: list, npairs: int, omega: float, nc: int, perspective: bool):
    """Build the fused kernels over the fields ``F`` for the level geometry ``geo``.

    Args:
        F: Taichi fields: ``wx, wy, dg, e, f, t`` (packed levels, (H, sum W_k)),
            ``z, b, r, p, q`` (level 0, (H, W)), ``sc`` (f64 scalars), ``pinv``,
            ``cidx`` (coarsest level), ``red`` (level-0 scratch), ``part``
            (f64, (ceil(H / 32), W): reduction partials), ``lab`` (component label per pixel, -1
            outside), ``csum, cden`` (f64 per-component accumulators), ``ccnt``
            (pixels per component).
        geo: ``[(off, h, w), ...]`` per level, level 0 first.
        npairs: Jacobi sweep pairs before and after each coarse correction.
        omega: Jacobi damping.
        nc: active cells of the coarsest level.
        perspective: the unknown is log-depth (PPN gradients, depth = exp).

    Returns:
        dict of kernels: ``rhs(nrm, fx, fy, cx, cy, s, min_nz)``,
        ``pcg_begin()``, ``pcg_iteration()``, ``residual()``,
        ``finish(out, reference)``, ``load(depth)`` (warm start from a depth map),
        ``mg_step()`` (one multigrid correction), ``rhs_only(...)``,
        ``scalars()`` (``sc`` as a vector), the builder ``frame(cycles)`` of
        the one-launch frame kernel (right-hand side, ``cycles`` corrections,
        depth), and for profiling ``vcycle_only()``, ``coarse_only()``, ``noop()``.
    """
    L = len(geo)
    h0, w0 = geo[0][1], geo[0][2]
    wx, wy, dg, e, f, t = F["wx"], F["wy"], F["dg"], F["e"], F["f"], F["t"]
    z, b, r, p, q, sc = F["z"], F["b"], F["r"], F["p"], F["q"], F["sc"]
    pinv, cidx, lab, csum, cden, ccnt = F["pinv"], F["cidx"], F["lab"], F["csum"], F["cden"], F["ccnt"]
    ncomp = ccnt.shape[0]
    om = omega

    red, part, part2 = F["red"], F["part"], F["part2"]
    fold0 = npairs == 1 and L > 1  # level 0's last sweep computed by its consumer
    CH = 32  # rows per chunk of the two-stage reductions
    NCH = (h0 + CH - 1) // CH

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
    def coarse_solve():
        """t = pinv f on the coarsest level's active cells (one thread per cell).

        ``pinv`` is symmetric (the pseudo-inverse of a symmetric matrix), so
        thread ``kk`` reads column ``kk``: neighbouring threads read
        neighbouring addresses (coalesced) instead of rows ``nc`` apart.
        """
        for kk in range(nc):
            s = f[cidx[kk, 0], cidx[kk, 1]] * 0
            for m in range(nc):
                s += pinv[m, kk] * f[cidx[m, 0], cidx[m, 1]]
            t[cidx[kk, 0], cidx[kk, 1]] = s

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
        for k in ti.static(range(L - 1)):
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
                f[ci, offc + cj] = (_res(2 * ci, 2 * cj, off, h, w) + _res(2 * ci, 2 * cj + 1, off, h, w)
                                    + _res(2 * ci + 1, 2 * cj, off, h, w) + _res(2 * ci + 1, 2 * cj + 1, off, h, w))
        coarse_solve()
        for k in ti.static(range(L - 2, -1, -1)):
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
    def _rhs(nrm: ti.template(), fx, fy, cx, cy, s, min_nz, norm: ti.template(), res: ti.template()):
        """b = -div of the mean steps of u (:func:`gpps.kernels.poisson.pixel_steps`,
        uniform weights); q and r hold the j- and i-steps meanwhile; with
        ``norm``, sc[7] = |b|^2; with ``res``, also f = b - A z (the first
        correction's residual, in the same pass)."""
        for i, j in ti.ndrange(h0, w0):
            a = ti.cast(0, ti.f64)
            c = ti.cast(0, ti.f64)
            if dg[i, j] > 0:
                a, c = pixel_steps(nrm, i, j, ti.static(perspective), fx, fy, cx, cy, s, min_nz)
            q[i, j] = ti.cast(a, q.dtype)  # step along j
            r[i, j] = ti.cast(c, r.dtype)  # step along i
        for i, j in ti.ndrange(h0, w0):
            v = div_mean_steps(q, r, wx, wy, i, j, h0, w0)
            b[i, j] = v
            if ti.static(norm):
                red[i, j] = ti.cast(_sq(v), red.dtype)
            if ti.static(res):
                d = dg[i, j]
                fv = v * 0
                if d > 0:
                    fv = v - d * z[i, j] + _neigh(z, wx, wy, i, j, 0, h0, w0)
                f[i, j] = fv
        if ti.static(norm):
            reduce_into(7)  # |b|^2

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
    def rhs(nrm: ti.types.ndarray(), fx: ti.f64, fy: ti.f64, cx: ti.f64, cy: ti.f64, s: ti.f64, min_nz: ti.f64):
        """b = -div of the steps from the normals (see ``_rhs``), |b|^2 in sc[7]."""
        _rhs(nrm, fx, fy, cx, cy, s, min_nz, True, False)

    @ti.kernel
    def pcg_begin():
        """Start the CG from the current z (see ``_begin``)."""
        _begin()

    @ti.kernel
    def rhs_begin(nrm: ti.types.ndarray(), fx: ti.f64, fy: ti.f64, cx: ti.f64, cy: ti.f64, s: ti.f64, min_nz: ti.f64):
        """``rhs`` and ``pcg_begin`` in one launch (the per-frame path)."""
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
        _correct(False)

    @ti.kernel
    def rhs_only(nrm: ti.types.ndarray(), fx: ti.f64, fy: ti.f64, cx: ti.f64, cy: ti.f64, s: ti.f64, min_nz: ti.f64):
        """``rhs`` without starting the CG (the multigrid-correction path)."""
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
    def _finish1(out: ti.template(), reference):
        """``_finish`` for one component in three tasks: the sums of u and exp(u) in one
        pass (sc[8], sc[9]; exp(u - m) sums to exp(-m) sum exp(u), so the perspective
        scale needs no second pass over the centred u), their column totals, the write."""
        for c, j in ti.ndrange(NCH, w0):
            if c == 0 and j == 0:
                sc[8] = 0
                sc[9] = 0
            a = ti.cast(0, ti.f64)
            x = ti.cast(0, ti.f64)
            for ii in range(CH):
                i = c * CH + ii
                if i < h0:
                    if lab[i, j] >= 0:
                        u = ti.cast(z[i, j], ti.f64)
                        a += u
                        if ti.static(perspective):
                            x += ti.exp(u)
            part[c, j] = a
            part2[c, j] = x
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
    def _finish(out: ti.template(), reference):
        """Fix each component's constant and write the depth.

        u's mean is set to 0 per component; orthographic depth = u + reference,
        perspective depth = exp(u) scaled so that each component's mean depth
        is ``reference`` (``reference <= 0``: left at exp(u), mean log-depth 0).
        z keeps the centred u (the next frame's warm start).
        """
        if ti.static(ncomp == 1):
            _finish1(out, reference)
        else:
            _finish_components(out, reference)

    @ti.func
    def _finish_components(out: ti.template(), reference):
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
        _finish(out, reference)

    @ti.func
    def _correct(res_ready: ti.template()):
        """z += M (b - A z): one V-cycle correction, no reductions (``res_ready``: f
        already holds b - A z, written by ``_rhs``)."""
        if ti.static(not res_ready):
            for i, j in ti.ndrange(h0, w0):
                f[i, j] = _res0(i, j)
        vcycle_levels()
        for i, j in ti.ndrange(h0, w0):
            z[i, j] += _mf0(i, j)

    frames = {}

    def frame(cycles: int):
        """The whole per-frame integration as *one* launch: right-hand side,
        ``cycles`` V-cycle corrections from the current ``z`` (the previous
        frame's solution, or 0 after a reset) and the depth write
        (``frame(nrm, out, fx, fy, cx, cy, s, min_nz, reference)``).  One
        kernel per ``cycles``, built on first use."""
        if cycles not in frames:
            @ti.kernel
            def _frame(nrm: ti.types.ndarray(), out: ti.types.ndarray(), fx: ti.f64, fy: ti.f64, cx: ti.f64,
                       cy: ti.f64, s: ti.f64, min_nz: ti.f64, reference: ti.f64):
                _rhs(nrm, fx, fy, cx, cy, s, min_nz, False, cycles > 0)
                for cyc in ti.static(range(cycles)):
                    _correct(cyc == 0)
                _finish(out, reference)

            frames[cycles] = _frame
        return frames[cycles]

    @ti.kernel
    def scalars() -> ti.types.vector(8, ti.f64):
        """All of ``sc`` in one read (one launch and one copy instead of one per element)."""
        return ti.Vector([sc[0], sc[1], sc[2], sc[3], sc[4], sc[5], sc[6], sc[7]], ti.f64)

    return {"rhs": rhs, "pcg_begin": pcg_begin, "rhs_begin": rhs_begin, "pcg_iteration": pcg_iteration, "residual": residual,
            "finish": finish, "load": load, "mg_step": mg_step, "rhs_only": rhs_only, "vcycle_only": vcycle_only,
            "coarse_only": coarse_only, "noop": noop, "scalars": scalars, "frame": frame}

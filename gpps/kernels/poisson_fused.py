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


def make_fused(F: dict, geo: list, npairs: int, omega: float, nc: int, perspective: bool, block: bool = False,
               block_threads: int = 512, block_cells: int = 4096):
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
        block: run every level of at most ``block_cells`` cells, down and up
            with the coarsest solve, as *one* task of a single thread block
            of ``block_threads`` threads that steps from pass to pass with
            ``ti.simt.block.sync()`` (CUDA only: on the GPU each task is a
            kernel launch of about 5 us, more than the small levels' work).

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
    NT = block_threads
    fused = npairs == 1  # one task per level and direction (the on-the-fly sweeps below)
    # first level handled inside the single block (CUDA): every level from K0 down
    K0 = L
    if block and fused:
        for k in range(L):
            if geo[k][1] * geo[k][2] <= block_cells:
                K0 = k
                break
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
    def _corr(i, j, off, offc, src: ti.template()):
        """The level's iterate (in t) plus the prolonged (injected) coarse correction (in src, coarse level)."""
        v = t[i, off + j] * 0
        if dg[i, off + j] > 0:
            v = t[i, off + j] + src[i // 2, offc + j // 2]
        return v

    @ti.func
    def _post_first(i, j, off, h, w, offc, src: ti.template()):
        """One damped Jacobi sweep applied to (iterate + coarse correction), computed on the fly."""
        d = dg[i, off + j]
        v = f[i, off + j] * 0
        if d > 0:
            nb = f[i, off + j] * 0
            if j > 0:
                nb += wx[i, off + j - 1] * _corr(i, j - 1, off, offc, src)
            if j < w - 1:
                nb += wx[i, off + j] * _corr(i, j + 1, off, offc, src)
            if i > 0:
                nb += wy[i - 1, off + j] * _corr(i - 1, j, off, offc, src)
            if i < h - 1:
                nb += wy[i, off + j] * _corr(i + 1, j, off, offc, src)
            v = (1 - om) * _corr(i, j, off, offc, src) + om * (f[i, off + j] + nb) / d
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
    def _coarse_cell(kk):
        """t = (pinv f)[kk] at the coarsest level's active cell kk.

        ``pinv`` is symmetric (the pseudo-inverse of a symmetric matrix), so
        thread ``kk`` reads column ``kk``: neighbouring threads read
        neighbouring addresses (coalesced) instead of rows ``nc`` apart.
        """
        s = f[cidx[kk, 0], cidx[kk, 1]] * 0
        for m in range(nc):
            s += pinv[m, kk] * f[cidx[m, 0], cidx[m, 1]]
        t[cidx[kk, 0], cidx[kk, 1]] = s

    @ti.func
    def coarse_solve():
        """t = pinv f on the coarsest level's active cells (one thread per cell)."""
        for kk in range(nc):
            _coarse_cell(kk)

    @ti.func
    def vcycle_tasks():
        """t_0 = M f_0: one V-cycle from zero, every level unrolled (the general form, any ``npairs``).

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
                e[i, off + j] = _post_first(i, j, off, h, w, offc, t)
            for i, j in ti.ndrange(h, w):
                t[i, off + j] = _jacobi_point(e, f, wx, wy, dg, i, j, off, h, w, om)
            for _ in ti.static(range(npairs - 1)):
                for i, j in ti.ndrange(h, w):
                    e[i, off + j] = _jacobi_point(t, f, wx, wy, dg, i, j, off, h, w, om)
                for i, j in ti.ndrange(h, w):
                    t[i, off + j] = _jacobi_point(e, f, wx, wy, dg, i, j, off, h, w, om)

    # ---------------------------------------------------------------- fewer tasks (npairs == 1)
    # The same V(2, 2)-cycle as vcycle_tasks.  Down, each level's two passes are
    # one task: the 8 pre-smoothed values around a 2x2 block are recomputed
    # rather than read after a task boundary (launches, not arithmetic, bound
    # these passes on a GPU).  Up stays two tasks per level: fusing it the same
    # way recomputes 25 stencils per pixel and made Taichi's compile 15x longer.
    # Level 0's last sweep is computed where it is consumed (``_mf0``).

    @ti.func
    def _pre_at(i, j, k: ti.template()):
        """``_pre`` at level k, 0 off the level."""
        off, h, w = ti.static(geo[k])
        v = f[0, 0] * 0
        if i >= 0 and i < h and j >= 0 and j < w:
            v = _pre(i, j, off, h, w)
        return v

    @ti.func
    def _res_vals(i, j, k: ti.template(), tc, tl, tr, tu, td):
        """Residual f - A t at level k's pixel (i, j) from the given centre / left / right / up / down t."""
        off, h, w = ti.static(geo[k])
        rr = f[0, 0] * 0
        if i < h and j < w:
            d = dg[i, off + j]
            if d > 0:
                nb = f[0, 0] * 0
                if j > 0:
                    nb += wx[i, off + j - 1] * tl
                if j < w - 1:
                    nb += wx[i, off + j] * tr
                if i > 0:
                    nb += wy[i - 1, off + j] * tu
                if i < h - 1:
                    nb += wy[i, off + j] * td
                rr = f[i, off + j] - d * tc + nb
        return rr

    @ti.func
    def _down_cell(ci, cj, k: ti.template()):
        """Level k's pre-smoothing at the 2x2 block of coarse cell (ci, cj), written to t, and the
        block's summed residual, written to level k+1's f.  The pre-smoothed values of the 4x4 patch
        around the block are computed here (a loop, so the stencil is compiled once) rather than read
        after a task boundary."""
        off, h, w = ti.static(geo[k])
        offc = ti.static(geo[k + 1][0])
        i0 = 2 * ci
        j0 = 2 * cj
        pv = ti.Vector([f[0, 0] * 0 for _ in ti.static(range(16))])  # patch rows i0-1..i0+2, cols j0-1..j0+2
        for q in range(16):
            a = q // 4
            c = q % 4
            if (a == 0 or a == 3) and (c == 0 or c == 3):
                continue  # the corners are not needed
            pv[q] = _pre_at(i0 - 1 + a, j0 - 1 + c, k)
        t[i0, off + j0] = pv[5]  # (i0, j0) is on the level: hc = ceil(h / 2), wc = ceil(w / 2)
        if j0 + 1 < w:
            t[i0, off + j0 + 1] = pv[6]
        if i0 + 1 < h:
            t[i0 + 1, off + j0] = pv[9]
            if j0 + 1 < w:
                t[i0 + 1, off + j0 + 1] = pv[10]
        f[ci, offc + cj] = (_res_vals(i0, j0, k, pv[5], pv[4], pv[6], pv[1], pv[9])
                            + _res_vals(i0, j0 + 1, k, pv[6], pv[5], pv[7], pv[2], pv[10])
                            + _res_vals(i0 + 1, j0, k, pv[9], pv[8], pv[10], pv[5], pv[13])
                            + _res_vals(i0 + 1, j0 + 1, k, pv[10], pv[9], pv[11], pv[6], pv[14]))

    @ti.func
    def block_part():
        """Levels K0 .. L-1 as one task of one thread block (CUDA): per level down, the pre-smoothing
        pass and the residual restriction; the dense coarsest solve; per level up (but level 0), the
        two post-smoothing sweeps; a block barrier after each pass (as a task boundary would be)."""
        ti.loop_config(block_dim=NT)
        for tid in range(NT):
            for k in ti.static(range(K0, L - 1)):
                off, h, w = ti.static(geo[k])
                offc, hc, wc = ti.static(geo[k + 1])
                for it in range((h * w + NT - 1) // NT):
                    cc = it * NT + tid
                    if cc < h * w:
                        t[cc // w, off + cc % w] = _pre(cc // w, cc % w, off, h, w)
                ti.simt.block.sync()
                for it in range((hc * wc + NT - 1) // NT):
                    cc = it * NT + tid
                    if cc < hc * wc:
                        ci = cc // wc
                        cj = cc % wc
                        f[ci, offc + cj] = (_res(2 * ci, 2 * cj, off, h, w) + _res(2 * ci, 2 * cj + 1, off, h, w)
                                            + _res(2 * ci + 1, 2 * cj, off, h, w)
                                            + _res(2 * ci + 1, 2 * cj + 1, off, h, w))
                ti.simt.block.sync()
            for it in range((nc + NT - 1) // NT):
                kk = it * NT + tid
                if kk < nc:
                    _coarse_cell(kk)
            ti.simt.block.sync()
            for k in ti.static(range(L - 2, max(K0, 1) - 1, -1)):
                off, h, w = ti.static(geo[k])
                offc = ti.static(geo[k + 1][0])
                for it in range((h * w + NT - 1) // NT):
                    cc = it * NT + tid
                    if cc < h * w:
                        e[cc // w, off + cc % w] = _post_first(cc // w, cc % w, off, h, w, offc, t)
                ti.simt.block.sync()
                for it in range((h * w + NT - 1) // NT):
                    cc = it * NT + tid
                    if cc < h * w:
                        t[cc // w, off + cc % w] = _jacobi_point(e, f, wx, wy, dg, cc // w, cc % w, off, h, w, om)
                ti.simt.block.sync()

    @ti.func
    def _up_point(i, j, k: ti.template(), src: ti.template()):
        """Level k's two post-smoothing sweeps at (i, j) in one pass: the first sweep at the pixel
        and its 4 neighbours in a loop (so the stencil is compiled once), then the second."""
        off, h, w = ti.static(geo[k])
        offc = ti.static(geo[k + 1][0])
        v = f[0, 0] * 0
        d = dg[i, off + j]
        if d > 0:
            ev = ti.Vector([f[0, 0] * 0 for _ in ti.static(range(5))])  # centre, left, right, up, down
            for q in range(5):
                ii = i
                jj = j
                if q == 1:
                    jj = j - 1
                elif q == 2:
                    jj = j + 1
                elif q == 3:
                    ii = i - 1
                elif q == 4:
                    ii = i + 1
                if ii >= 0 and ii < h and jj >= 0 and jj < w:
                    ev[q] = _post_first(ii, jj, off, h, w, offc, src)
            nb = f[0, 0] * 0
            if j > 0:
                nb += wx[i, off + j - 1] * ev[1]
            if j < w - 1:
                nb += wx[i, off + j] * ev[2]
            if i > 0:
                nb += wy[i - 1, off + j] * ev[3]
            if i < h - 1:
                nb += wy[i, off + j] * ev[4]
            v = (1 - om) * ev[0] + om * (f[i, off + j] + nb) / d
        return v

    TOP = min(K0, L - 1)  # levels below TOP descend as tasks; from K0 on, in the block (or as tasks)

    def _src(k):
        """Where level k+1's corrected iterate lives when level k ascends: e for a level that
        ascended as one fused task (1 <= k+1 < TOP), t for the coarsest and the block's levels."""
        return e if 1 <= k + 1 < TOP else t

    @ti.func
    def vcycle_levels():
        """Every pass of one V-cycle from zero on level 0's f except level 0's ascent (``_mf0``).

        Down, one task per level (``_down_cell``); the levels from K0 and the
        coarsest solve in one single-block task (CUDA) or as tasks; up, one task
        per level (``_up_point``, into e), level 0's left to the consumer.
        """
        if ti.static(not fused):
            vcycle_tasks()
        else:
            for k in ti.static(range(TOP)):
                hc, wc = ti.static(geo[k + 1][1], geo[k + 1][2])
                for ci, cj in ti.ndrange(hc, wc):
                    _down_cell(ci, cj, k)
            if ti.static(K0 < L):
                block_part()
            else:
                coarse_solve()
            for k in ti.static(range(TOP - 1, 0, -1)):
                off, h, w = ti.static(geo[k])
                for i, j in ti.ndrange(h, w):
                    e[i, off + j] = _up_point(i, j, k, ti.static(_src(k)))

    @ti.func
    def _mf0(i, j):
        """``(M f_0)[i, j]``: level 0's result of the V-cycle run by ``vcycle_levels``."""
        v = t[0, 0] * 0
        if ti.static(fused and L > 1):
            v = _up_point(i, j, 0, ti.static(_src(0)))
        else:
            v = t[i, j]
        return v

    @ti.func
    def vcycle():
        """e_0 = M f_0 (one V-cycle from zero on level 0's f)."""
        vcycle_levels()
        for i, j in ti.ndrange(h0, w0):
            e[i, j] = _mf0(i, j)

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
                    p[i, j] = e[i, j]
                    acc += _mul(r[i, j], e[i, j])
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
                    acc += _mul(r[i, j], e[i, j])
            part[c, j] = acc
        stage2(RZN)
        beta = sc[RZN] * 0
        if sc[RZ] > 0:
            beta = sc[RZN] / sc[RZ]
        sc[RZ] = sc[RZN]
        sc[5] = beta
        for i, j in ti.ndrange(h0, w0):
            p[i, j] = e[i, j] + ti.cast(sc[5], p.dtype) * p[i, j]

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

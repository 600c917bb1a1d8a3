"""The persistent and hybrid frame kernels of the fused Poisson integrator: phases met at grid barriers.

Part of :func:`gpps.kernels.poisson_fused.make_fused` (see its module for the
frame and the namespace ``ns`` the factories read).  Each Taichi task costs
about 3 us of device time and 5 us of host time, so on CUDA the small levels
(or the whole frame) run as *one* persistent task of ``nblocks x bd`` threads
whose phases meet at software grid barriers (about 2 us a barrier on an H100,
``perf/taichi_grid_barrier.py``).  The barrier needs every block resident at
once; a block that waits too long sets a flag instead of hanging (see
:func:`persistent_builders`).  Only device code lives here.
"""

from gpps._taichi import ti
from gpps.kernels.grid_barrier import make_gsync
from gpps.kernels.poisson import _jacobi_point


def grid_funcs(ns, nblocks: int, bd: int):
    """The grid barrier and the persistent levels for ``nblocks x bd`` threads (see ``persistent``).

    Args:
        ns: the namespace of :func:`gpps.kernels.poisson_fused.make_fused`.
        nblocks: blocks of the persistent task.
        bd: threads per block.

    Returns:
        ``(NT, gsync, plevels)``: the thread count and the ti.funcs ``gsync(tid, gen)`` (a grid
        barrier) and ``plevels(tid, gen, top)`` (the V-cycle from level ``top`` down and back up).
    """
    wx, wy, dg, e, f, t, bar, geof = ns.wx, ns.wy, ns.dg, ns.e, ns.f, ns.t, ns.bar, ns.geof
    L, nc, npairs, om, fold0, cuda = ns.L, ns.nc, ns.npairs, ns.om, ns.fold0, ns.cuda
    _pre, _post_first, _restrict_at, _coarse_at = ns._pre, ns._post_first, ns._restrict_at, ns._coarse_at
    if not cuda and nblocks * bd != 1:
        raise ValueError(f"nblocks, bd: off CUDA the persistent kernel runs as one thread (1, 1), got ({nblocks}, {bd})")
    NT = nblocks * bd

    # the warp-uniform grid barrier shared with BiNI's persistent IRLS (its first warp polls in step: a lone
    # spinning lane beside its warp waiting at the block barrier deadlocked some kernels on an H100); off CUDA
    # its one-thread stand-in
    gsync = make_gsync(bar, nblocks, bd, cuda)

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


def persistent_phases(ns, NT: int) -> dict:
    """The level-0 phases of the persistent frame after the V-cycle, cells strided over ``NT`` threads.

    Args:
        ns: the namespace of :func:`gpps.kernels.poisson_fused.make_fused`.
        NT: threads of the persistent task.

    Returns:
        dict of ti.funcs: ``_pupdate(tid, last)`` (z += M f per (row chunk, column); with ``last``,
        the frame's last cycle, also the sums of u and exp(u): one component into ``part``/``part2``,
        several into ``csum``/``cden``, one atomic per run of equal labels), ``_ptotals(tid)`` (one
        component: the column totals into ``csum[0]``, ``cden[0]``), ``_pwrite(tid, out, reference)``
        (u centred per component, the depth written).
    """
    z, lab, part, part2, csum, cden, ccnt = ns.z, ns.lab, ns.part, ns.part2, ns.csum, ns.cden, ns.ccnt
    h0, w0, CH, NCH, NIT, ncomp, perspective = ns.h0, ns.w0, ns.CH, ns.NCH, ns.NIT, ns.ncomp, ns.perspective
    _mf0 = ns._mf0
    n0 = h0 * w0

    @ti.func
    def _pupdate(tid, last):
        """z += M f, per (row chunk, column); the last cycle also sums u and exp(u)."""
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

    @ti.func
    def _ptotals(tid):
        """One component: csum[0], cden[0] += the column totals of ``part``, ``part2``."""
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

    @ti.func
    def _pwrite(tid, out: ti.template(), reference: ti.template()):
        """Centre u per component (the next frame's warm start) and write the depth."""
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

    return {"_pupdate": _pupdate, "_ptotals": _ptotals, "_pwrite": _pwrite}


def persistent_builders(ns) -> dict:
    """The builders of the persistent frame kernels (one kernel per argument set, built on first use).

    Args:
        ns: the namespace of :func:`gpps.kernels.poisson_fused.make_fused` (with ``_frame_kernel``).

    Returns:
        dict: ``persistent(nblocks, bd)`` and ``hybrid(cycles, top, nblocks, bd)``.
    """
    bar, f, csum, cden = ns.bar, ns.f, ns.csum, ns.cden
    L, h0, w0, ncomp = ns.L, ns.h0, ns.w0, ns.ncomp
    _rhs_at, _res0, _update_z, _frame_kernel = ns._rhs_at, ns._res0, ns._update_z, ns._frame_kernel
    vdown, vup = ns.vdown, ns.vup
    pframes = {}

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
        that waits more than :data:`gpps.kernels.grid_barrier.LIMIT` polls sets ``bar[1]`` and lets the frame finish with
        wrong values instead of hanging; :class:`StreamIntegrator` checks the flag on its
        first frame and falls back to fewer blocks, then to :func:`frame`.  On the CPU
        (whose thread pool gives no such residency) it runs only as one thread,
        ``persistent(1, 1)``: every phase in order, which tests its arithmetic.
        """
        key = (nblocks, bd)
        if key in pframes:
            return pframes[key]
        NT, gsync, plevels = grid_funcs(ns, nblocks, bd)
        n0 = h0 * w0

        P = persistent_phases(ns, NT)
        _pupdate, _ptotals, _pwrite = P["_pupdate"], P["_ptotals"], P["_pwrite"]

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
                    # z += M f, per (row chunk, column); the last cycle also sums u and exp(u)
                    last = cyc == cycles - 1
                    _pupdate(tid, last)
                    gen = gsync(tid, gen)
                if ti.static(ncomp == 1):
                    _ptotals(tid)
                    gen = gsync(tid, gen)
                # centre u per component (the next frame's warm start) and write the depth
                _pwrite(tid, out, reference)

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
        NT, gsync, plevels = grid_funcs(ns, nblocks, bd)

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

    return {"persistent": persistent, "hybrid": hybrid}

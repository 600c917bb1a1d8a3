"""The integrator's whole multigrid-preconditioned CG solve as one persistent Taichi task (device code only).

:func:`gpps.kernels.poisson.pcg_iteration` runs a PCG iteration as one Taichi launch of about 40 parallel tasks
(``A p``, the updates, every level of the V-cycle, the new direction), and the host reads ``|r|^2`` every
``check_every`` iterations.  Each task costs the host about 5-7 us in Taichi's runtime and a kernel call 20-100 us
in Python: at 256^2 a 14-iteration solve keeps the host busy for several milliseconds while the GPU works about one
(perf/results/s23: ``integrator.pcg``, 9.7 ms of host time against 1.2 ms of GPU time).  Here the start, every
iteration and the stopping test run in *one* task of ``nblocks x bd`` threads whose phases meet at software grid
barriers (:func:`gpps.kernels.grid_barrier.make_gsync`, about 2 us each), as BiNI's persistent IRLS
(:func:`gpps.kernels.bini.make_irls_persistent`) and the stream's persistent frame do.

The arithmetic is :mod:`gpps.kernels.poisson`'s, through its per-point funcs (``_start_point``, ``_apply_point``,
``_update_point``, ``_jacobi_point``, ``_neigh``) in the same order of phases as ``pcg_start`` / ``pcg_iteration``
(:func:`gpps.kernels.poisson._vcycle`: per level ``2 npairs`` Jacobi sweeps from zero, the residual, the 2 x 2
restriction; the coarsest level's exact pseudo-inverse; per level the injected correction and ``2 npairs``
sweeps), and the stopping rule of :meth:`gpps.pipeline.integration.Integrator._iterate`: ``|r|^2`` compared with
``tol^2 |b|^2`` after every ``check_every``-th iteration (and at the cap), and the float32 stagnation stop
(``|r|^2 > 0.8`` of the previous check's, and this check's or the previous one's below ``1e-8 |b|^2``; the fused
launches then return the iterate of the lowest residual checked below that floor, this task the last one).  What
differs is the order of the float64
additions of the dot products: each sum is strided over the threads, tree-reduced per block in shared memory and
added by one float64 atomic a block (on CUDA), so ``alpha`` and ``beta`` may differ from the fused launch's in
their last bits.  The iteration that meets the tolerance skips its V-cycle and direction (they touch neither the
solution nor ``|r|^2``).

The barrier needs every block resident at once: a block that polls too long sets ``bar[1]`` and the solve finishes
with wrong values instead of hanging; the integrator checks the flag after a kernel's first launch and falls back to
the fused launches (:meth:`gpps.pipeline.integration.Integrator._iterate`).  Off CUDA the kernel runs as one thread
(``nblocks = bd = 1``): every phase in order and every sum in pixel order, which tests its arithmetic.
"""

from gpps._taichi import ti
from gpps.kernels.block_sum import BLOCK, make_acc_sums
from gpps.kernels.grid_barrier import make_gsync
from gpps.kernels.poisson import (
    _apply_point,
    _inject_at,
    _jacobi_point,
    _mul,
    _residual_at,
    _restrict_at,
    _sq,
    _start_point,
    _update_point,
)

# slots of the persistent solve's float64 accumulator ``acc`` (its length is at least NACC)
A_BB, A_RR0, A_RZ0, A_ITS, A_RES = 0, 1, 2, 3, 4  # |b|^2, the start's |r|^2 and r.Mr, iterations, last |r|^2 checked
A_PQ, A_RR, A_RZ = 5, 8, 11  # three slots each, by iteration mod 3
NACC = 14


def make_pcg_persistent(d: dict, geom: tuple, omega: float, npairs: int, nblocks: int, bd: int, cuda: bool):
    """The integrator's multigrid PCG (start, iterations, stopping test) as one persistent task.

    Args:
        d: the integrator's device fields (:meth:`gpps.pipeline.integration.Integrator._ensure_device`): ``z``
            (the start, then the solution), ``b``, ``r``, ``p``, ``q``, the packed levels ``wx``, ``wy``, ``dg``,
            ``e``, ``f``, ``t``, the coarsest level's ``pinv`` and ``cidx``, and ``acc`` (f64, >= :data:`NACC`),
            ``bar`` (i32 (2,): barrier arrivals, timeout flag), ``geo`` (i32 (levels, 3): ``geom`` as a field).
        geom: ``((off, h, w), ...)`` per level, finest first (the level count and level 0's size are compiled in;
            the V-cycle reads the levels from ``geo`` at run time).
        omega: Jacobi damping; npairs: sweep pairs before and after each coarse correction.
        nblocks, bd: the task's blocks and threads per block (``bd`` = :data:`gpps.kernels.block_sum.BLOCK` on
            CUDA; ``(1, 1)`` off CUDA).
        cuda: the CUDA build (shared-memory block sums, grid barriers) or the one-thread build.

    Returns:
        the kernel ``pcg(nc, tol, cap, check_every, stagnation)``: ``nc`` the coarsest level's active cells,
        ``tol`` the relative residual, ``cap`` the iteration cap, ``stagnation`` 1 for the float32 stop.  On
        return ``z`` holds the solution and ``acc`` the iterations (``A_ITS``), ``|b|^2`` (``A_BB``) and the last
        ``|r|^2`` the stopping rule read (``A_RES``): one read for the host.
    """
    if cuda and bd != BLOCK:
        raise ValueError(f"bd: expected {BLOCK} threads per block on CUDA, got {bd}")
    if not cuda and nblocks * bd != 1:
        raise ValueError(f"nblocks, bd: off CUDA the persistent kernel runs as one thread (1, 1), "
                         f"got ({nblocks}, {bd})")
    NT = nblocks * bd
    z, b, r, p, q = d["z"], d["b"], d["r"], d["p"], d["q"]
    wx, wy, dg, e, f, t = d["wx"], d["wy"], d["dg"], d["e"], d["f"], d["t"]
    pinv, cidx, acc, bar, geo = d["pinv"], d["cidx"], d["acc"], d["bar"], d["geo"]
    L = len(geom)
    H0, W0 = geom[0][1], geom[0][2]
    N0 = H0 * W0
    dtype = z.dtype
    om = float(omega)

    gsync = make_gsync(bar, nblocks, bd, cuda)
    red, red2 = make_acc_sums(acc, bd, cuda)

    @ti.func
    def sweep(tid, gen, src: ti.template(), dst: ti.template(), off, h, w):
        """One damped Jacobi sweep src -> dst on a level (``poisson._sweeps``' loop), then a barrier."""
        for kk in range((h * w + NT - 1) // NT):
            c = tid + kk * NT
            if c < h * w:
                dst[c // w, off + c % w] = _jacobi_point(src, f, wx, wy, dg, c // w, c % w, off, h, w, om)
        return gsync(tid, gen)

    @ti.func
    def vcycle(tid, gen, nc):
        """e = M f at level 0 (``poisson._vcycle``), a phase per barrier; returns the next barrier number.  The
        levels and sweeps are runtime loops over ``geo`` (unrolled, the ~40 inlined barriers of a 6-level cycle
        took Taichi's CUDA build a minute to compile)."""
        g = gen
        for k in range(L - 1):
            off, h, w = geo[k, 0], geo[k, 1], geo[k, 2]
            offc, hc, wc = geo[k + 1, 0], geo[k + 1, 1], geo[k + 1, 2]
            for _ in range(npairs):
                g = sweep(tid, g, e, t, off, h, w)
                g = sweep(tid, g, t, e, off, h, w)
            for kk in range((h * w + NT - 1) // NT):  # the residual (poisson._down)
                c = tid + kk * NT
                if c < h * w:
                    _residual_at(e, f, t, wx, wy, dg, c // w, c % w, off, h, w)
            g = gsync(tid, g)
            for kk in range((hc * wc + NT - 1) // NT):  # the restriction (sums of 2 x 2 blocks)
                c = tid + kk * NT
                if c < hc * wc:
                    _restrict_at(e, f, t, c // wc, c % wc, off, h, w, offc)
            g = gsync(tid, g)
        for kk in range((nc + NT - 1) // NT):  # the coarsest level's exact solve (poisson._coarse_exact)
            c = tid + kk * NT
            if c < nc:
                s = f[cidx[c, 0], cidx[c, 1]] * 0
                for m in range(nc):
                    s += pinv[c, m] * f[cidx[m, 0], cidx[m, 1]]
                e[cidx[c, 0], cidx[c, 1]] = s
        g = gsync(tid, g)
        for kq in range(L - 1):
            k = L - 2 - kq
            off, h, w = geo[k, 0], geo[k, 1], geo[k, 2]
            offc = geo[k + 1, 0]
            for kk in range((h * w + NT - 1) // NT):  # the injected correction (poisson._up)
                c = tid + kk * NT
                if c < h * w:
                    _inject_at(e, dg, c // w, c % w, off, offc)
            g = gsync(tid, g)
            for _ in range(npairs):
                g = sweep(tid, g, e, t, off, h, w)
                g = sweep(tid, g, t, e, off, h, w)
        return g

    @ti.kernel
    def pcg(nc: ti.i32, tol: ti.f64, cap: ti.i32, check_every: ti.i32, stagnation: ti.i32):
        bar[0] = 0
        bar[1] = 0
        for i in range(NACC):
            acc[i] = 0
        ti.loop_config(block_dim=bd, block_dim_adaptive=False)
        for tid in range(NT):
            pad = ti.simt.block.SharedArray((BLOCK,), ti.f64) if ti.static(cuda) else 0.0
            pad2 = ti.simt.block.SharedArray((BLOCK,), ti.f64) if ti.static(cuda) else 0.0
            gen = 1
            # |b|^2 (residual_norm from 0) and the start: r = f = b - A z, e = 0, |r|^2 (poisson._cg_start)
            bbp = ti.cast(0, ti.f64)
            rrp = ti.cast(0, ti.f64)
            for kk in range((N0 + NT - 1) // NT):
                c = tid + kk * NT
                if c < N0:
                    i, j = c // W0, c % W0
                    if dg[i, j] > 0:
                        bbp += _sq(b[i, j])
                    rrp += _start_point(z, b, r, e, f, wx, wy, dg, i, j, H0, W0)
            red2(pad, pad2, tid, bbp, A_BB, rrp, A_RR0)
            gen = gsync(tid, gen)
            bb = acc[A_BB]
            tol2 = tol * tol * bb
            rr = acc[A_RR0]
            its = 0
            if bb > 0 and rr > tol2:
                # the first V-cycle and direction: p = M r, rz = r . M r (poisson._cg_first_direction)
                gen = vcycle(tid, gen, nc)
                rzp = ti.cast(0, ti.f64)
                for kk in range((N0 + NT - 1) // NT):
                    c = tid + kk * NT
                    if c < N0:
                        i, j = c // W0, c % W0
                        p[i, j] = e[i, j]
                        rzp += _mul(r[i, j], e[i, j])
                red(pad, tid, rzp, A_RZ0)
                gen = gsync(tid, gen)
                rz = acc[A_RZ0]
                while its < cap:
                    s = its % 3
                    # q = A p, p.q (poisson._cg_step)
                    pqp = ti.cast(0, ti.f64)
                    for kk in range((N0 + NT - 1) // NT):
                        c = tid + kk * NT
                        if c < N0:
                            pqp += _apply_point(p, q, wx, wy, dg, c // W0, c % W0, H0, W0)
                    red(pad, tid, pqp, A_PQ + s)
                    if tid == 0:  # the slots of iteration its + 1 (= its - 2: read by every thread before now)
                        nx = (its + 1) % 3
                        acc[A_PQ + nx] = 0
                        acc[A_RR + nx] = 0
                        acc[A_RZ + nx] = 0
                    gen = gsync(tid, gen)
                    pq = acc[A_PQ + s]
                    alpha = ti.cast(0, ti.f64)
                    if pq > 0:
                        alpha = rz / pq
                    a = ti.cast(alpha, dtype)
                    # z += a p, r -= a q, f = r, e = 0, |r|^2
                    rrp = ti.cast(0, ti.f64)
                    for kk in range((N0 + NT - 1) // NT):
                        c = tid + kk * NT
                        if c < N0:
                            rrp += _update_point(z, r, p, q, e, f, a, c // W0, c % W0)
                    red(pad, tid, rrp, A_RR + s)
                    gen = gsync(tid, gen)
                    its += 1
                    if its % check_every == 0 or its >= cap:  # Integrator._iterate's check
                        prev = rr
                        rr = acc[A_RR + s]
                        if rr <= tol2:
                            break
                        if stagnation != 0 and rr > 0.8 * prev and ti.min(rr, prev) < 1e-8 * bb:
                            break  # (the float32 floor: stalled there, or thrown back up from it)
                    if its >= cap:
                        break
                    # the V-cycle, then rz' = r . M r, p = M r + (rz'/rz) p (poisson._cg_direction)
                    gen = vcycle(tid, gen, nc)
                    rzp = ti.cast(0, ti.f64)
                    for kk in range((N0 + NT - 1) // NT):
                        c = tid + kk * NT
                        if c < N0:
                            i, j = c // W0, c % W0
                            rzp += _mul(r[i, j], e[i, j])
                    red(pad, tid, rzp, A_RZ + s)
                    gen = gsync(tid, gen)
                    rzn = acc[A_RZ + s]
                    beta = ti.cast(0, ti.f64)
                    if rz > 0:
                        beta = rzn / rz
                    rz = rzn
                    bt = ti.cast(beta, dtype)
                    for kk in range((N0 + NT - 1) // NT):
                        c = tid + kk * NT
                        if c < N0:
                            i, j = c // W0, c % W0
                            p[i, j] = e[i, j] + bt * p[i, j]
                    gen = gsync(tid, gen)
            if tid == 0:
                acc[A_ITS] = its
                acc[A_RES] = rr
        # (the kernel's end orders everything before the host's read)

    return pcg

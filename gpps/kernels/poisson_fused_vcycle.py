"""The multigrid V-cycle of the fused Poisson kernels: smoothing, restriction, prolongation, coarse solve.

Part of :func:`gpps.kernels.poisson_fused.make_fused`: the factories here read
the fields, the level geometry and the ti.funcs built before them from its
namespace ``ns`` (see there) and return their ti.funcs, closed over the same
fields.  Same operator as :func:`gpps.kernels.poisson.down` / ``up`` (2x2
aggregation, injection, damped Jacobi, an exact pseudo-inverse on the coarsest
level), every level unrolled with ``ti.static``.  Only device code lives here.
"""

from gpps._taichi import ti
from gpps.kernels.poisson import _jacobi_point, _neigh


def level_funcs(ns) -> dict:
    """The per-point stencils of one level (cells of a task, or strided over a persistent task's threads).

    Args:
        ns: the namespace of :func:`gpps.kernels.poisson_fused.make_fused` (fields ``wx, wy, dg, f, t,
            pinv, cidx, cmap, fcv``; ``om``, ``nc``).

    Returns:
        dict of ti.funcs: ``_pre`` (the pre-smoothing pair from zero), ``_corr`` and ``_post_first``
        (the first post-smoothing sweep on iterate + prolonged correction), ``_res``,
        ``_restrict_at`` (residual restricted to the coarse cell), ``_coarse_at`` (one cell of
        the coarsest solve).
    """
    wx, wy, dg, f, t = ns.wx, ns.wy, ns.dg, ns.f, ns.t
    pinv, cidx, cmap, fcv = ns.pinv, ns.cidx, ns.cmap, ns.fcv
    om, nc = ns.om, ns.nc

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

    return {"_pre": _pre, "_corr": _corr, "_post_first": _post_first, "_res": _res, "_restrict_at": _restrict_at,
            "_coarse_at": _coarse_at}


def vcycle_funcs(ns) -> dict:
    """One V-cycle from zero on level 0's f, its descent and ascent separately (for the hybrid frame).

    Args:
        ns: the namespace of :func:`gpps.kernels.poisson_fused.make_fused` (fields ``wx, wy, dg, e, f, t,
            bar``; ``geo``, ``L``, ``h0``, ``w0``, ``npairs``, ``om``, ``nc``, ``fold0``; the ti.funcs of
            :func:`level_funcs`).

    Returns:
        dict of ti.funcs: ``coarse_solve``, ``vcycle_levels``, ``vdown``, ``vup``, ``_mf0`` (level 0's
        result, its last sweep folded into the consumer), ``vcycle`` (t_0 = M f_0).
    """
    wx, wy, dg, e, f, t, bar = ns.wx, ns.wy, ns.dg, ns.e, ns.f, ns.t, ns.bar
    geo, L, h0, w0, npairs, om, nc, fold0 = ns.geo, ns.L, ns.h0, ns.w0, ns.npairs, ns.om, ns.nc, ns.fold0
    _pre, _post_first, _restrict_at, _coarse_at = ns._pre, ns._post_first, ns._restrict_at, ns._coarse_at

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

    return {"coarse_solve": coarse_solve, "vcycle_levels": vcycle_levels, "vdown": vdown, "vup": vup, "_mf0": _mf0,
            "vcycle": vcycle}

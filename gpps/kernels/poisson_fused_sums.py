"""Reductions, the depth update and the finish of the fused Poisson kernels.

Part of :func:`gpps.kernels.poisson_fused.make_fused`: the factories here read
the fields, constants and the ti.funcs built before them from its namespace
``ns`` (see there) and return their ti.funcs, closed over the same fields.
Every sum is accumulated in float64: two-stage reductions over (row chunk,
column) items (``CH`` rows a chunk) instead of same-address atomics per pixel,
per-component sums over runs of equal labels, and on CUDA warp shuffles with
one atomic per warp.  Only device code lives here.
"""

from gpps._taichi import ti


def reduce_funcs(ns) -> dict:
    """Two-stage float64 reductions of level-0 values into ``sc`` or per-component fields.

    Args:
        ns: the namespace of :func:`gpps.kernels.poisson_fused.make_fused` (fields ``sc, part, red,
            lab``; ``h0``, ``w0``, ``CH``, ``NCH``, ``ncomp``).

    Returns:
        dict of ti.funcs ``stage2``, ``reduce_into``, ``comp_sums``.
    """
    sc, part, red, lab = ns.sc, ns.part, ns.red, ns.lab
    h0, w0, CH, NCH, ncomp = ns.h0, ns.w0, ns.CH, ns.NCH, ns.ncomp

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

    return {"stage2": stage2, "reduce_into": reduce_into, "comp_sums": comp_sums}


def warp_funcs(ns) -> dict:
    """CUDA warp reductions: the one-component sums of the last z update without a task of their own.

    Args:
        ns: the namespace of :func:`gpps.kernels.poisson_fused.make_fused` (fields ``sc, slot, wcnt``;
            ``perspective``, ``NSLOT``, ``NW``).

    Returns:
        dict of ti.funcs ``_shfl64``, ``_wsum``, ``_warp_total``.
    """
    sc, slot, wcnt = ns.sc, ns.slot, ns.wcnt
    perspective, NSLOT, NW = ns.perspective, ns.NSLOT, ns.NW

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

    return {"_shfl64": _shfl64, "_wsum": _wsum, "_warp_total": _warp_total}


def update_funcs(ns) -> dict:
    """The depth update ``z += M f_0``, with the one-component sums of the new u fused into it.

    Args:
        ns: the namespace of :func:`gpps.kernels.poisson_fused.make_fused` (fields ``z, sc, part, part2,
            lab``; ``h0``, ``w0``, ``CH``, ``NCH``, ``NIT``, ``NPAD``, ``ncomp``, ``perspective``, ``wsums``;
            ``_mf0`` and the ti.funcs of :func:`warp_funcs`).

    Returns:
        dict of ti.funcs ``_chunk_sums``, ``_chunk_acc``, ``_update_z``.
    """
    z, sc, part, part2, lab = ns.z, ns.sc, ns.part, ns.part2, ns.lab
    h0, w0, CH, NCH, NIT, NPAD = ns.h0, ns.w0, ns.CH, ns.NCH, ns.NIT, ns.NPAD
    ncomp, perspective, wsums = ns.ncomp, ns.perspective, ns.wsums
    _mf0, _warp_total = ns._mf0, ns._warp_total

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

    return {"_chunk_sums": _chunk_sums, "_chunk_acc": _chunk_acc, "_update_z": _update_z}


def finish_funcs(ns) -> dict:
    """The finish: each component's constant fixed, the depth written.

    Args:
        ns: the namespace of :func:`gpps.kernels.poisson_fused.make_fused` (fields ``z, sc, part, part2,
            red, lab, csum, cden, ccnt``; ``h0``, ``w0``, ``NCH``, ``ncomp``, ``perspective``, ``wsums``;
            ``_chunk_sums`` and ``comp_sums``).

    Returns:
        dict of ti.funcs ``_finish1``, ``_finish``, ``_finish_components``.
    """
    z, sc, part, part2, red, lab = ns.z, ns.sc, ns.part, ns.part2, ns.red, ns.lab
    csum, cden, ccnt = ns.csum, ns.cden, ns.ccnt
    h0, w0, NCH, ncomp, perspective, wsums = ns.h0, ns.w0, ns.NCH, ns.ncomp, ns.perspective, ns.wsums
    _chunk_sums, comp_sums = ns._chunk_sums, ns.comp_sums

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

    return {"_finish1": _finish1, "_finish": _finish, "_finish_components": _finish_components}

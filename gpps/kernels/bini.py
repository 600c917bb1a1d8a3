"""Taichi device math of bilateral normal integration (BiNI, Cao et al., ECCV 2022).

The unknown ``u`` (depth, or log-depth under the perspective camera) lives on
the ``n`` valid pixels in a compact layout: pixel ``p`` has the neighbour
indices ``nb[p, 0..3]`` = right (j+1), left (j-1), down (i+1), up (i-1), -1
where there is none.  Each pixel owns BiNI's four one-sided equations in the
multiplied form (the residual is ``N D - m``, no division by ``N``):

    j:  N_j (u_right - u_p) - m_j,    N_j (u_p - u_left) - m_j
    i:  N_i (u_down  - u_p) - m_i,    N_i (u_p - u_up)   - m_i

with weights ``w_j, 1 - w_j`` and ``w_i, 1 - w_i``; a missing neighbour's
difference is 0 (its equation is the constant ``m^2``, as in BiNI's matrices).
IRLS re-weighting (BiNI eq. (20)): ``w_j = sigmoid(k ((N_j D_left)^2 -
(N_j D_right)^2))`` from the current ``u``, so the side with the smaller jump
gets the weight.  For fixed weights, the normal equations are the weighted
graph Laplacian ``A u = b`` with edge weight ``W = N_a^2 w+_a + N_b^2 w-_b``
on the edge ``a -> b`` and flux ``F = N_a m_a w+_a + N_b m_b w-_b``; they are
solved by BiNI's Jacobi-preconditioned conjugate gradient (diagonal clipped
at 1e-5), warm-started from the previous iterate.

Every reduction is accumulated in float64.  The CG iteration is two parallel
loops and nothing serial: the direction update ``p = z + beta p`` is fused into
the next ``A p`` (each pixel forms its own and its neighbours' new ``p``; the
directions ping-pong between two buffers), and the scalars live in three sets
of fields (the iteration modulo 3), so a loop only reads the sets the previous
loops finished and zeroes the set the next loop accumulates into.  The stopping test (``|r|^2 <= tol^2 |b|^2``, at least one iteration, as
BiNI) is made by every pixel alike from the finished column, so one launch runs
several iterations (unrolled, ``ti.static``) and turns into no-ops once the
solve is done: the host checks once per launch and never overshoots.  :func:`make_bini` builds the kernels
over one set of fields (closed over, not passed: a launch has no per-argument
cost), from factories by topic: the IRLS weights and energy, the system
assembly with the CG start, and the CG iteration (parallel or serial).

Only device code lives here; allocation and orchestration are in
:mod:`gpps.pipeline.integration_bini`.
"""

from gpps._taichi import ti
from gpps.kernels.block_sum import BLOCK, block_total, block_total2, make_acc_sums
from gpps.kernels.grid_barrier import make_gsync

# indices into the scalar field ``sc``
BB, ENERGY, ITS, TOTAL = range(4)
NSC = 4



@ti.func
def _sigmoid(x):
    """Logistic ``1 / (1 + exp(-x))`` without overflow (float64)."""
    v = ti.cast(0.0, ti.f64)
    if x >= 0:
        v = 1.0 / (1.0 + ti.exp(-x))
    else:
        e = ti.exp(x)
        v = e / (1.0 + e)
    return v


@ti.func
def _diffs(x: ti.template(), nb: ti.template(), p):
    """One-sided differences (right, left, down, up) of ``x`` at compact pixel ``p`` (0 where no neighbour)."""
    xp = x[p]
    dr = xp * 0
    dl = xp * 0
    dd = xp * 0
    du = xp * 0
    if nb[p, 0] >= 0:
        dr = x[nb[p, 0]] - xp
    if nb[p, 1] >= 0:
        dl = xp - x[nb[p, 1]]
    if nb[p, 2] >= 0:
        dd = x[nb[p, 2]] - xp
    if nb[p, 3] >= 0:
        du = xp - x[nb[p, 3]]
    return dr, dl, dd, du


def make_bini(F: dict, unroll: int = 8, serial: bool = False):
    """Build the BiNI kernels over the fields ``F``.

    Args:
        F: Taichi fields, float64 of length ``capacity`` unless noted: ``x`` (the
            unknown), ``b, r, z, p0, p1, q`` (CG), ``Nj, Ni, mj, mi`` (equations),
            ``wj, wi`` (forward weights), ``Wr, Wd, Fr, Fd`` (edge weights and
            fluxes to the right / down neighbour), ``dinv`` (Jacobi), ``nb`` (i32
            (capacity, 4): right, left, down, up, -1 none), ``pix`` (i32
            (capacity, 2): row, column), ``sc`` (f64 (NSC,): scalars), ``pq, rr,
            rz, done``: lists of three f64 (1,) fields, the CG scalars of the
            iterations ``t mod 3`` (separate fields, so that no loop reads or writes the
            field it sums into and Taichi keeps its sums warp/thread-local instead of
            one float64 atomic a pixel).
        unroll: CG iterations per launch of ``cg`` (a multiple of 6).
        serial: ``cg`` runs on one thread with local sums (the CPU build:
            Taichi's thread-pool dispatch of a loop costs more than a loop over
            ~1e5 pixels, and a sum into a field element is an atomic per pixel); the
            other kernels' sums then run in pixel order too (deterministic results).
            Otherwise (the CUDA build) each loop's sums are reduced in shared memory
            per block of :data:`BLOCK` threads, one float64 atomic a block: Taichi
            launches at least a saturating grid of threads, so its thread-local sums
            would end in one atomic a pixel, and float64 atomics on one address
            serialise (77-148 us a loop on DiLiGenT bear's 40 670 pixels on an H100,
            0.65 s for the map against 0.116 s with the block sums,
            perf/results/bini_launch_bear_H100.json).

    Returns:
        dict of kernels, each taking the pixel count ``n`` first:
        ``energy(n)`` (``sc[ENERGY]`` of ``x`` under the current weights),
        ``reweight(n, k)`` (BiNI's weight update, then ``sc[ENERGY]``),
        ``begin(n)`` (assemble the system from the weights, CG start: ``r = b - A x``,
        ``z = D^-1 r``), ``cg(n, tol2, maxit)`` (``unroll`` gated Jacobi-PCG
        iterations; ``done[(unroll - 1) % 3][0]`` tells the host it is done,
        ``rr[(sc[ITS] - 1) % 3][0]`` is the last ``|r|^2``),
        ``scatter(n, out)`` (``out[i, j] = x[p]``).
    """
    if unroll % 6:
        raise ValueError(f"unroll: expected a multiple of 6 (direction buffers by 2, scalar columns by 3), got {unroll}")
    x, pix = F["x"], F["pix"]
    cg = _cg_serial_kernel(F, unroll) if serial else _cg_block_kernel(F, unroll)
    K = {**_weight_kernels(F, serial), "begin": _begin_kernel(F, serial), "cg": cg}

    @ti.kernel
    def scatter(n: ti.i32, out: ti.types.ndarray()):
        for p in range(n):
            out[pix[p, 0], pix[p, 1]] = x[p]

    K["scatter"] = scatter
    K.update(_transfer_kernels(F))
    return K


def _transfer_kernels(F: dict) -> dict:
    """One-launch uploads and fetches of the stage's per-pixel arrays (each host array crosses once, where a
    field's ``from_numpy`` / ``to_numpy`` a field would cost a launch and a copy each).

    Returns:
        dict of kernels over the ``cap`` entries of ``F`` (entries ``>= n`` are padding, set as by a zero
        upload: 0, and -1 for the neighbours):
        ``load_index(n, a)``: ``a`` (n, 6) int32: the neighbours (right, left, down, up) and the pixel's
        (row, column) into ``nb`` and ``pix``;
        ``load(n, a)``: ``a`` (n, 5) float64: ``Nj, Ni, mj, mi`` and the start ``x``; the weights ``wj, wi``
        set to BiNI's 0.5 and the scalars ``sc`` zeroed;
        ``gather(n, out)``: ``out`` (n, 3) float64 gets ``x, wj, wi``.
    """
    cap = F["cap"]
    x, nb, pix, wj, wi, sc = F["x"], F["nb"], F["pix"], F["wj"], F["wi"], F["sc"]
    Nj, Ni, mj, mi = F["Nj"], F["Ni"], F["mj"], F["mi"]

    @ti.kernel
    def load_index(n: ti.i32, a: ti.types.ndarray()):
        for p in range(cap):
            if p < n:
                for k in ti.static(range(4)):
                    nb[p, k] = a[p, k]
                for k in ti.static(range(2)):
                    pix[p, k] = a[p, 4 + k]
            else:
                for k in ti.static(range(4)):
                    nb[p, k] = -1
                for k in ti.static(range(2)):
                    pix[p, k] = 0

    @ti.kernel
    def load(n: ti.i32, a: ti.types.ndarray()):
        for p in range(cap):
            if p < n:
                Nj[p] = a[p, 0]
                Ni[p] = a[p, 1]
                mj[p] = a[p, 2]
                mi[p] = a[p, 3]
                x[p] = a[p, 4]
            else:
                Nj[p] = 0
                Ni[p] = 0
                mj[p] = 0
                mi[p] = 0
                x[p] = 0
            wj[p] = 0.5
            wi[p] = 0.5
        for i in range(NSC):
            sc[i] = 0

    @ti.kernel
    def gather(n: ti.i32, out: ti.types.ndarray()):
        for p in range(n):
            out[p, 0] = x[p]
            out[p, 1] = wj[p]
            out[p, 2] = wi[p]

    return {"load_index": load_index, "load": load, "gather": gather}


def _pixel_funcs(F: dict):
    """The per-pixel ti.funcs over the fields ``F`` that the task kernels and the persistent kernel share:

    * ``edges(p)``: the edge weights and fluxes to the right / down neighbour from the IRLS weights
      (``Wr, Fr, Wd, Fd`` at ``p``);
    * ``rhs(p)``: ``b`` and the clipped Jacobi inverse ``dinv`` at ``p`` (after every pixel's ``edges``);
    * ``apply(v, p)``: ``(A v)_p = sum_e W_e (v_p - v_q)`` over the edges of ``p``;
    * ``residuals(p)``: the four one-sided residuals ``N D - m`` and the multiplied differences
      ``(el, er, eu, ed)`` BiNI's weights compare;
    * ``reweight(p, k)``: BiNI's new weights at ``p`` (written) and the pixel's energy under them.
    """
    x, Nj, Ni, mj, mi, wj, wi, nb = F["x"], F["Nj"], F["Ni"], F["mj"], F["mi"], F["wj"], F["wi"], F["nb"]
    Wr, Wd, Fr, Fd, b, dinv = F["Wr"], F["Wd"], F["Fr"], F["Fd"], F["b"], F["dinv"]

    @ti.func
    def edges(p):
        W1 = Wr[p] * 0
        F1 = Wr[p] * 0
        W2 = Wr[p] * 0
        F2 = Wr[p] * 0
        o = nb[p, 0]
        if o >= 0:
            W1 = Nj[p] * Nj[p] * wj[p] + Nj[o] * Nj[o] * (1 - wj[o])
            F1 = Nj[p] * mj[p] * wj[p] + Nj[o] * mj[o] * (1 - wj[o])
        o = nb[p, 2]
        if o >= 0:
            W2 = Ni[p] * Ni[p] * wi[p] + Ni[o] * Ni[o] * (1 - wi[o])
            F2 = Ni[p] * mi[p] * wi[p] + Ni[o] * mi[o] * (1 - wi[o])
        Wr[p] = W1
        Fr[p] = F1
        Wd[p] = W2
        Fd[p] = F2

    @ti.func
    def rhs(p):
        d = Wr[p] + Wd[p]
        v = -Fr[p] - Fd[p]
        o = nb[p, 1]
        if o >= 0:
            d += Wr[o]
            v += Fr[o]
        o = nb[p, 3]
        if o >= 0:
            d += Wd[o]
            v += Fd[o]
        b[p] = v
        dinv[p] = 1.0 / ti.max(d, 1e-5)

    @ti.func
    def apply(v: ti.template(), p):
        vp = v[p]
        s = vp * 0
        o = nb[p, 0]
        if o >= 0:
            s += Wr[p] * (vp - v[o])
        o = nb[p, 1]
        if o >= 0:
            s += Wr[o] * (vp - v[o])
        o = nb[p, 2]
        if o >= 0:
            s += Wd[p] * (vp - v[o])
        o = nb[p, 3]
        if o >= 0:
            s += Wd[o] * (vp - v[o])
        return s

    @ti.func
    def residuals(p):
        dr, dl, dd, du = _diffs(x, nb, p)
        a, c = Nj[p], Ni[p]
        er, el, ed, eu = a * dr, a * dl, c * dd, c * du
        return er - mj[p], el - mj[p], ed - mi[p], eu - mi[p], el, er, eu, ed

    @ti.func
    def reweight(p, k):
        rr, rl, rd, ru, el, er, eu, ed = residuals(p)
        w1 = _sigmoid(k * (el * el - er * er))
        w2 = _sigmoid(k * (eu * eu - ed * ed))
        wj[p] = w1
        wi[p] = w2
        return w1 * rr * rr + (1 - w1) * rl * rl + w2 * rd * rd + (1 - w2) * ru * ru

    return {"edges": edges, "rhs": rhs, "apply": apply, "residuals": residuals, "reweight": reweight}


def _weight_kernels(F: dict, serial: bool = False) -> dict:
    """BiNI's energy and IRLS weight update over the fields ``F`` (see :func:`make_bini`).

    ``serial`` (the CPU build): the loops run on one thread, so their float64 sums are added in pixel order and
    a result does not depend on how Taichi's threads were scheduled (a parallel loop's sums end in atomics).

    Returns:
        dict of kernels ``energy(n)``, ``reweight(n, k)``.
    """
    wj, wi, sc = F["wj"], F["wi"], F["sc"]
    px = _pixel_funcs(F)
    residuals, reweight_at = px["residuals"], px["reweight"]

    @ti.kernel
    def energy(n: ti.i32):
        sc[ENERGY] = 0
        ti.loop_config(serialize=serial)
        for p in range(n):
            rr, rl, rd, ru, _, _, _, _ = residuals(p)
            w1, w2 = wj[p], wi[p]
            sc[ENERGY] += w1 * rr * rr + (1 - w1) * rl * rl + w2 * rd * rd + (1 - w2) * ru * ru

    @ti.kernel
    def reweight(n: ti.i32, k: ti.f64):
        sc[ENERGY] = 0
        ti.loop_config(serialize=serial)
        for p in range(n):
            sc[ENERGY] += reweight_at(p, k)

    return {"energy": energy, "reweight": reweight}


def _begin_kernel(F: dict, serial: bool = False):
    """The kernel ``begin(n)`` over the fields ``F``: the system assembled from the weights, the CG started
    (see :func:`make_bini`); ``serial`` as in :func:`_weight_kernels` (its sums in pixel order)."""
    x, b, r, z, p0, dinv, sc = F["x"], F["b"], F["r"], F["z"], F["p0"], F["dinv"], F["sc"]
    pqf, rrf, rzf, dnf = F["pq"], F["rr"], F["rz"], F["done"]
    px = _pixel_funcs(F)
    edges, rhs, _apply = px["edges"], px["rhs"], px["apply"]

    @ti.kernel
    def begin(n: ti.i32):
        for p in range(n):
            edges(p)
        for p in range(n):
            rhs(p)
        sc[BB] = 0
        ti.static(rzf[2])[0] = 0
        ti.loop_config(serialize=serial)
        for p in range(n):
            rv = b[p] - _apply(x, p)
            zv = dinv[p] * rv
            r[p] = rv
            z[p] = zv
            p0[p] = 0  # the "previous direction" of iteration 0: p_0 = z_0
            ti.static(rzf[2])[0] += rv * zv  # iteration -1's column: r_0 . z_0
            sc[BB] += b[p] * b[p]
        ti.static(rzf[1])[0] = 1.0  # iteration -2's r.z: any nonzero value (it multiplies p = 0)
        ti.static(rrf[2])[0] = 1e300  # BiNI always runs at least one iteration
        ti.static(dnf[2])[0] = 0
        ti.static(pqf[0])[0] = 0
        sc[ITS] = 0

    return begin


def _ap_fused_func(F: dict):
    """The ti.func ``_ap_fused(p, beta, pold)`` over the fields ``F`` (both CG builds use it)."""
    z, Wr, Wd, nb = F["z"], F["Wr"], F["Wd"], F["nb"]

    @ti.func
    def _ap_fused(p, beta, pold: ti.template()):
        """(p_new, (A p_new)_p) with p_new = z + beta pold formed on the fly for p and its neighbours."""
        pp = z[p] + beta * pold[p]
        s = pp * 0
        o = nb[p, 0]
        if o >= 0:
            s += Wr[p] * (pp - (z[o] + beta * pold[o]))
        o = nb[p, 1]
        if o >= 0:
            s += Wr[o] * (pp - (z[o] + beta * pold[o]))
        o = nb[p, 2]
        if o >= 0:
            s += Wd[p] * (pp - (z[o] + beta * pold[o]))
        o = nb[p, 3]
        if o >= 0:
            s += Wd[o] * (pp - (z[o] + beta * pold[o]))
        return pp, s

    return _ap_fused


def _cg_update_func(F: dict):
    """The ti.func ``_cg_update(p, a, pdir)`` over the fields ``F`` (every CG build uses it): the step of pixel
    ``p`` along the direction ``pdir`` (``x += a p``, ``r -= a q``, ``z = D^-1 r``); returns its terms of
    ``|r|^2`` and ``r . z``."""
    x, r, z, q, dinv = F["x"], F["r"], F["z"], F["q"], F["dinv"]

    @ti.func
    def _cg_update(p, a, pdir: ti.template()):
        x[p] += a * pdir[p]
        rv = r[p] - a * q[p]
        r[p] = rv
        zv = dinv[p] * rv
        z[p] = zv
        return rv * rv, rv * zv

    return _cg_update


def _cg_block_kernel(F: dict, unroll: int):
    """``cg`` with block sums (the CUDA build, see :func:`make_bini`): ``unroll`` gated Jacobi-PCG
    iterations, each two parallel loops over ``n`` rounded up to whole blocks (the extra threads add 0):
    (1) ``p_t = z_t + beta_t p_{t-1}`` (fused), ``q = A p_t``, ``p_t . q`` and the stopping test of
    iteration t-1; (2) ``alpha = r.z / p.q``, ``x += alpha p``, ``r -= alpha q``, ``z = D^-1 r``, ``|r|^2``,
    ``r.z``.  Each sum is tree-reduced in shared memory and added to its field by one atomic a block."""
    p0, p1, q, sc = F["p0"], F["p1"], F["q"], F["sc"]
    pqf, rrf, rzf, dnf = F["pq"], F["rr"], F["rz"], F["done"]
    _ap_fused = _ap_fused_func(F)
    _cg_update = _cg_update_func(F)

    @ti.kernel
    def cg_block(n: ti.i32, tol2: ti.f64, maxit: ti.i32):
        for t in ti.static(range(unroll)):
            c, c1, c2 = ti.static(t % 3, (t + 2) % 3, (t + 1) % 3)
            pold, pnew = ti.static((p0, p1) if t % 2 == 0 else (p1, p0))
            ti.loop_config(block_dim=BLOCK)
            for p in range((n + BLOCK - 1) // BLOCK * BLOCK):
                tid = p % BLOCK
                pad = ti.simt.block.SharedArray((BLOCK,), ti.f64)
                done = ti.static(dnf[c1])[0] != 0 or ti.static(rrf[c1])[0] <= tol2 * sc[BB] or sc[ITS] >= maxit
                beta = ti.static(rzf[c1])[0] / ti.static(rzf[c2])[0]
                pq = ti.cast(0, ti.f64)
                if p < n and not done:
                    pp, s = _ap_fused(p, beta, pold)
                    q[p] = s
                    pnew[p] = pp
                    pq = pp * s
                pad[tid] = pq
                block_total(pad, tid)
                if tid == 0:
                    ti.atomic_add(ti.static(pqf[c])[0], pad[0])
                if p == 0:
                    ti.static(dnf[c])[0] = ti.cast(done, ti.f64)
                    if not done:
                        ti.static(rrf[c])[0] = 0
                        ti.static(rzf[c])[0] = 0
            ti.loop_config(block_dim=BLOCK)
            for p in range((n + BLOCK - 1) // BLOCK * BLOCK):
                tid = p % BLOCK
                pr = ti.simt.block.SharedArray((BLOCK,), ti.f64)
                pz = ti.simt.block.SharedArray((BLOCK,), ti.f64)
                done = ti.static(dnf[c])[0] != 0
                pq = ti.static(pqf[c])[0]
                rr = ti.cast(0, ti.f64)
                rz = ti.cast(0, ti.f64)
                if p < n and not done and pq != 0:
                    u, v = _cg_update(p, ti.static(rzf[c1])[0] / pq, pnew)
                    rr = u
                    rz = v
                pr[tid] = rr
                pz[tid] = rz
                block_total2(pr, pz, tid)
                if tid == 0:
                    ti.atomic_add(ti.static(rrf[c])[0], pr[0])
                    ti.atomic_add(ti.static(rzf[c])[0], pz[0])
                if p == 0:
                    ti.static(pqf[(t + 1) % 3])[0] = 0
                    if not done:
                        sc[ITS] += 1
                        sc[TOTAL] += 1

    return cg_block


def _cg_serial_kernel(F: dict, unroll: int):
    """``cg`` on one thread (the CPU build, see :func:`make_bini`)."""
    p0, p1, q, sc = F["p0"], F["p1"], F["q"], F["sc"]
    pqf, rrf, rzf, dnf = F["pq"], F["rr"], F["rz"], F["done"]
    _ap_fused = _ap_fused_func(F)
    _cg_update = _cg_update_func(F)

    @ti.kernel
    def cg_serial(n: ti.i32, tol2: ti.f64, maxit: ti.i32):
        # the same iteration on one thread (the CPU build): the sums are plain local
        # accumulators (no atomics), in pixel order, and a finished solve skips its loops
        for t in ti.static(range(unroll)):
            c, c1, c2 = ti.static(t % 3, (t + 2) % 3, (t + 1) % 3)
            pold, pnew = ti.static((p0, p1) if t % 2 == 0 else (p1, p0))
            done = ti.static(dnf[c1])[0] != 0 or ti.static(rrf[c1])[0] <= tol2 * sc[BB] or sc[ITS] >= maxit
            ti.static(dnf[c])[0] = ti.cast(done, ti.f64)
            if not done:
                beta = ti.static(rzf[c1])[0] / ti.static(rzf[c2])[0]
                pq = ti.cast(0, ti.f64)
                for p in range(n):  # inside a branch: a serial loop
                    pp, v = _ap_fused(p, beta, pold)
                    q[p] = v
                    pnew[p] = pp
                    pq += pp * v
                ti.static(pqf[c])[0] = pq
                rr = ti.cast(0, ti.f64)
                rz = ti.cast(0, ti.f64)
                if pq != 0:
                    a = ti.static(rzf[c1])[0] / pq
                    for p in range(n):
                        u, v = _cg_update(p, a, pnew)
                        rr += u
                        rz += v
                    sc[ITS] += 1
                    sc[TOTAL] += 1
                ti.static(rrf[c])[0] = rr
                ti.static(rzf[c])[0] = rz

    return cg_serial


# slots of the persistent kernel's accumulators ``acc`` (f64): three per CG sum (the iteration mod 3),
# then the start's r.z and |b|^2 and the energy
A_PQ, A_RR, A_RZ, A_RZ0, A_BB, A_E, A_ITS = 0, 3, 6, 9, 10, 11, 12
NACC = 13


def make_irls_persistent(F: dict, nblocks: int, bd: int, cuda: bool):
    """One IRLS iteration of BiNI (system assembly, the whole Jacobi-PCG solve, reweighting and energy) as
    *one* task of ``nblocks x bd`` threads whose phases meet at software grid barriers.

    The arithmetic is :func:`make_bini`'s (``begin``, ``cg``, ``reweight``), through the same per-pixel
    funcs (:func:`_pixel_funcs`, ``_ap_fused``): the same fused direction update, the same stopping test
    (``|r|^2 <= tol^2 |b|^2`` after at least one iteration, or ``maxit``), the same ``pq != 0`` guard.
    What changes is the launch shape: the block build launches two tasks per CG iteration and the host
    polls a flag every 6 iterations (on DiLiGenT
    bear 447 launches of 6 iterations at about 160 us each, perf/results/bini_launch_bear_H100.json);
    here a CG iteration is two phases and two grid barriers (about 2 us each on an H100,
    perf/taichi_grid_barrier.py), and the host launches once per IRLS iteration.  Each sum is
    tree-reduced per block in shared memory and added by one float64 atomic a block into a slot
    of ``acc`` (the CG iteration mod 3: a slot is zeroed two iterations after every thread has
    read it); every thread reads the finished sums after the barrier, so all of them take the
    same branch and leave the CG loop together.

    The barrier needs every block resident at once: a block that waits more than ``LIMIT`` polls
    sets ``bar[1]`` and the iteration finishes with wrong values instead of hanging (the stage
    checks the flag on its first launch and falls back to the block build).  Off CUDA it runs as
    one thread (``nblocks = bd = 1``): every phase in order, sums in pixel order, which tests
    its arithmetic against the serial build.

    Args:
        F: the fields of :func:`make_bini` plus ``acc`` (f64 (NACC,)) and ``bar`` (i32 (2,)).
        nblocks, bd: the task's blocks and threads per block (``bd`` = :data:`BLOCK` on CUDA).
        cuda: the CUDA build (shared-memory block sums) or the one-thread build.

    Returns:
        the kernel ``irls(n, tol2, maxit, k)``: on return ``x`` is the solve's result, ``wj, wi``
        the new weights, and ``acc`` holds the energy (``A_E``), the CG iterations (``A_ITS``),
        ``|b|^2`` (``A_BB``) and the last ``|r|^2`` (``A_RR + (its - 1) % 3``): one read for the host.
    """
    if cuda and bd != BLOCK:
        raise ValueError(f"bd: expected {BLOCK} threads per block on CUDA, got {bd}")
    if not cuda and nblocks * bd != 1:
        raise ValueError(f"nblocks, bd: off CUDA the persistent kernel runs as one thread (1, 1), "
                         f"got ({nblocks}, {bd})")
    NT = nblocks * bd
    x, b, r, z, p0, p1, q, dinv = F["x"], F["b"], F["r"], F["z"], F["p0"], F["p1"], F["q"], F["dinv"]
    acc, bar = F["acc"], F["bar"]
    _ap_fused = _ap_fused_func(F)
    _cg_update = _cg_update_func(F)
    px = _pixel_funcs(F)
    edges, rhs, _apply, reweight_at = px["edges"], px["rhs"], px["apply"], px["reweight"]

    gsync = make_gsync(bar, nblocks, bd, cuda)
    red, red2 = make_acc_sums(acc, bd, cuda)

    @ti.func
    def cg_iter(tid, gen, n, t, beta, rz_prev, pa: ti.template(), pb: ti.template(), pad: ti.template(),
                pad2: ti.template()):
        """CG iteration ``t`` (directions ``pa`` -> ``pb``): returns (gen, pq, |r|^2, r.z)."""
        c = t % 3
        pq = ti.cast(0, ti.f64)
        for kk in range((n + NT - 1) // NT):
            p = tid + kk * NT
            if p < n:
                pp, s = _ap_fused(p, beta, pa)
                q[p] = s
                pb[p] = pp
                pq += pp * s
        red(pad, tid, pq, A_PQ + c)
        if tid == 0:  # the slot of iteration t + 1 (= t - 2, read by every thread before t - 1's barriers)
            nx = (t + 1) % 3
            acc[A_PQ + nx] = 0
            acc[A_RR + nx] = 0
            acc[A_RZ + nx] = 0
        g = gsync(tid, gen)
        pqt = acc[A_PQ + c]
        rr = ti.cast(0, ti.f64)
        rz = ti.cast(0, ti.f64)
        if pqt != 0:
            a = rz_prev / pqt
            for kk in range((n + NT - 1) // NT):
                p = tid + kk * NT
                if p < n:
                    u, v = _cg_update(p, a, pb)
                    rr += u
                    rz += v
        red2(pad, pad2, tid, rr, A_RR + c, rz, A_RZ + c)
        g = gsync(tid, g)
        return g, pqt, acc[A_RR + c], acc[A_RZ + c]

    @ti.kernel
    def irls(n: ti.i32, tol2: ti.f64, maxit: ti.i32, k: ti.f64):
        bar[0] = 0
        for i in range(NACC):
            acc[i] = 0
        ti.loop_config(block_dim=bd, block_dim_adaptive=False)
        for tid in range(NT):
            pad = ti.simt.block.SharedArray((BLOCK,), ti.f64) if ti.static(cuda) else 0.0
            pad2 = ti.simt.block.SharedArray((BLOCK,), ti.f64) if ti.static(cuda) else 0.0
            gen = 1
            # the system from the weights (make_bini's begin): edge weights and fluxes, then b and D^-1
            for kk in range((n + NT - 1) // NT):
                p = tid + kk * NT
                if p < n:
                    edges(p)
            gen = gsync(tid, gen)
            for kk in range((n + NT - 1) // NT):
                p = tid + kk * NT
                if p < n:
                    rhs(p)
            gen = gsync(tid, gen)
            # the CG start: r = b - A x, z = D^-1 r, p_{-1} = 0
            rz0 = ti.cast(0, ti.f64)
            bb = ti.cast(0, ti.f64)
            for kk in range((n + NT - 1) // NT):
                p = tid + kk * NT
                if p < n:
                    rv = b[p] - _apply(x, p)
                    zv = dinv[p] * rv
                    r[p] = rv
                    z[p] = zv
                    p0[p] = 0
                    rz0 += rv * zv
                    bb += b[p] * b[p]
            red2(pad, pad2, tid, rz0, A_RZ0, bb, A_BB)
            gen = gsync(tid, gen)
            bbt = acc[A_BB]
            rz_prev = acc[A_RZ0]
            rz_pp = ti.cast(1.0, ti.f64)  # (multiplies p_{-1} = 0)
            its = 0
            while True:  # two iterations a pass: the directions ping-pong p0 -> p1 -> p0
                if its >= maxit:
                    break
                gen, pq, rr, rz = cg_iter(tid, gen, n, its, rz_prev / rz_pp, rz_prev, p0, p1, pad, pad2)
                rz_pp = rz_prev
                rz_prev = rz
                its += 1
                if rr <= tol2 * bbt or its >= maxit:
                    break
                gen, pq, rr, rz = cg_iter(tid, gen, n, its, rz_prev / rz_pp, rz_prev, p1, p0, pad, pad2)
                rz_pp = rz_prev
                rz_prev = rz
                its += 1
                if rr <= tol2 * bbt:
                    break
            # BiNI's reweighting and the energy under the new weights
            e = ti.cast(0, ti.f64)
            for kk in range((n + NT - 1) // NT):
                p = tid + kk * NT
                if p < n:
                    e += reweight_at(p, k)
            red(pad, tid, e, A_E)
            if tid == 0:
                acc[A_ITS] = its
        # (the kernel's end orders everything before the host's read)

    return irls

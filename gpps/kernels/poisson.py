"""Taichi device math for the masked Poisson integrator (4.20).

The discrete problem is the weighted graph Laplacian of the mask (the masked
5-point Laplacian with natural, i.e. Neumann, boundary conditions)::

    (A u)_a = dg_a u_a - sum_{b ~ a} w_ab u_b,       dg_a = sum_{b ~ a} w_ab

Edge weights are stored per pixel: ``wx[i, j]`` joins ``(i, j)`` and
``(i, j+1)``, ``wy[i, j]`` joins ``(i, j)`` and ``(i+1, j)``; a pixel with
``dg == 0`` is outside the mask.

Multigrid levels are packed side by side in one 2D field (level ``k`` starts
at column ``off_k``), so each kernel is compiled once per field set and takes
the level geometry ``(off, h, w)`` as scalar arguments.  Coarsening is
aggregation of 2x2 blocks (restriction = sum, prolongation = injection), the
coarse operator is rediscretised from the fine edge weights (see
:func:`gpps.host.poisson.build_levels`).  Several Jacobi sweeps are
unrolled per kernel (``ti.static``) to keep launches few; the conjugate
gradient scalars live in a small float64 device field (dot products are
accumulated in float64 whatever the field precision) so the solve runs without
host syncs except the periodic residual check.  The kernels that sum (the
conjugate gradient's and ``residual_norm``) have two builds, picked by their
last argument: per-pixel ``sc[K] +=`` (the CPU) and per-block tree sums in
shared memory (CUDA, :mod:`gpps.kernels.block_sum`), the same arithmetic.

Only device code lives here; allocation and orchestration are in
:mod:`gpps.pipeline.integration`.
"""


from gpps._taichi import ti
from gpps.kernels.block_sum import BLOCK, block_add, whole_blocks

# indices into the scalar field ``sc``
RZ, PQ, RR, ALPHA, RZN = 0, 1, 2, 3, 4


@ti.func
def _neigh(x: ti.template(), wx: ti.template(), wy: ti.template(), i, j, off, h, w):
    """sum_b w_ab x_b over the 4-neighbours of (i, j) of a level at column off."""
    s = x[i, off + j] * 0
    if j > 0:
        s += wx[i, off + j - 1] * x[i, off + j - 1]
    if j < w - 1:
        s += wx[i, off + j] * x[i, off + j + 1]
    if i > 0:
        s += wy[i - 1, off + j] * x[i - 1, off + j]
    if i < h - 1:
        s += wy[i, off + j] * x[i + 1, off + j]
    return s


@ti.func
def _jacobi_point(src: ti.template(), f: ti.template(), wx: ti.template(), wy: ti.template(), dg: ti.template(),
                  i, j, off, h, w, omega: ti.template()):
    """One damped Jacobi update of pixel (i, j); 0 outside the mask."""
    d = dg[i, off + j]
    v = src[i, off + j] * 0
    if d > 0:
        v = (1 - omega) * src[i, off + j] + omega * (f[i, off + j] + _neigh(src, wx, wy, i, j, off, h, w)) / d
    return v


@ti.func
def _sweeps(e: ti.template(), f: ti.template(), t: ti.template(), wx: ti.template(), wy: ti.template(),
            dg: ti.template(), off: ti.template(), h: ti.template(), w: ti.template(), omega: ti.template(),
            npairs: ti.template()):
    """``2 * npairs`` damped Jacobi sweeps on ``A e = f`` at one level (ping-pong through t)."""
    for _ in ti.static(range(npairs)):
        for i, j in ti.ndrange(h, w):
            t[i, off + j] = _jacobi_point(e, f, wx, wy, dg, i, j, off, h, w, omega)
        for i, j in ti.ndrange(h, w):
            e[i, off + j] = _jacobi_point(t, f, wx, wy, dg, i, j, off, h, w, omega)


@ti.func
def _residual_at(e: ti.template(), f: ti.template(), t: ti.template(), wx: ti.template(), wy: ti.template(),
                 dg: ti.template(), i, j, off, h, w):
    """t = f - A e at pixel (i, j) of a level (0 outside the mask)."""
    d = dg[i, off + j]
    r = f[i, off + j] * 0
    if d > 0:
        r = f[i, off + j] - d * e[i, off + j] + _neigh(e, wx, wy, i, j, off, h, w)
    t[i, off + j] = r


@ti.func
def _restrict_at(e: ti.template(), f: ti.template(), t: ti.template(), ci, cj, off, h, w, offc):
    """Coarse cell (ci, cj): f = the sum of its 2 x 2 fine residuals t, e = 0."""
    s = t[2 * ci, off + 2 * cj]
    if 2 * cj + 1 < w:
        s += t[2 * ci, off + 2 * cj + 1]
    if 2 * ci + 1 < h:
        s += t[2 * ci + 1, off + 2 * cj]
        if 2 * cj + 1 < w:
            s += t[2 * ci + 1, off + 2 * cj + 1]
    f[ci, offc + cj] = s
    e[ci, offc + cj] = 0


@ti.func
def _inject_at(e: ti.template(), dg: ti.template(), i, j, off, offc):
    """Pixel (i, j) of a level plus the coarse correction of its cell (mask pixels only)."""
    if dg[i, off + j] > 0:
        e[i, off + j] += e[i // 2, offc + j // 2]


@ti.func
def _down(e: ti.template(), f: ti.template(), t: ti.template(), wx: ti.template(), wy: ti.template(),
          dg: ti.template(), off: ti.template(), h: ti.template(), w: ti.template(), offc: ti.template(),
          hc: ti.template(), wc: ti.template(), omega: ti.template(), npairs: ti.template()):
    """V-cycle descent at one level: pre-smooth from e = 0, residual, restrict."""
    _sweeps(e, f, t, wx, wy, dg, off, h, w, omega, npairs)
    for i, j in ti.ndrange(h, w):
        _residual_at(e, f, t, wx, wy, dg, i, j, off, h, w)
    for ci, cj in ti.ndrange(hc, wc):
        _restrict_at(e, f, t, ci, cj, off, h, w, offc)


@ti.func
def _up(e: ti.template(), f: ti.template(), t: ti.template(), wx: ti.template(), wy: ti.template(),
        dg: ti.template(), off: ti.template(), h: ti.template(), w: ti.template(), offc: ti.template(),
        omega: ti.template(), npairs: ti.template()):
    """V-cycle ascent at one level: add the injected coarse correction, post-smooth."""
    for i, j in ti.ndrange(h, w):
        _inject_at(e, dg, i, j, off, offc)
    _sweeps(e, f, t, wx, wy, dg, off, h, w, omega, npairs)


@ti.func
def _coarse_exact(e: ti.template(), f: ti.template(), cidx: ti.template(), pinv: ti.template(), n: ti.template()):
    """e = pinv(A_c) f on the coarsest level's n active cells (dense, exact)."""
    for k in range(n):
        s = f[cidx[k, 0], cidx[k, 1]] * 0
        for m in range(n):
            s += pinv[k, m] * f[cidx[m, 0], cidx[m, 1]]
        e[cidx[k, 0], cidx[k, 1]] = s


@ti.kernel
def smooth(e: ti.template(), f: ti.template(), t: ti.template(), wx: ti.template(), wy: ti.template(),
           dg: ti.template(), off: ti.i32, h: ti.i32, w: ti.i32, omega: ti.template(), npairs: ti.template()):
    """``2 * npairs`` damped Jacobi sweeps on ``A e = f`` (ping-pong through t)."""
    _sweeps(e, f, t, wx, wy, dg, off, h, w, omega, npairs)


@ti.kernel
def down(e: ti.template(), f: ti.template(), t: ti.template(), wx: ti.template(), wy: ti.template(),
         dg: ti.template(), off: ti.i32, h: ti.i32, w: ti.i32, offc: ti.i32, hc: ti.i32, wc: ti.i32,
         omega: ti.template(), npairs: ti.template()):
    """V-cycle descent at one level (:func:`_down`)."""
    _down(e, f, t, wx, wy, dg, off, h, w, offc, hc, wc, omega, npairs)


@ti.kernel
def up(e: ti.template(), f: ti.template(), t: ti.template(), wx: ti.template(), wy: ti.template(),
       dg: ti.template(), off: ti.i32, h: ti.i32, w: ti.i32, offc: ti.i32, omega: ti.template(), npairs: ti.template()):
    """V-cycle ascent at one level (:func:`_up`)."""
    _up(e, f, t, wx, wy, dg, off, h, w, offc, omega, npairs)


@ti.kernel
def coarse_exact(e: ti.template(), f: ti.template(), cidx: ti.template(), pinv: ti.template(), n: ti.i32):
    """e = pinv(A_c) f on the coarsest level's n active cells (dense, exact)."""
    _coarse_exact(e, f, cidx, pinv, n)


# ----------------------------------------------------------------------------- conjugate gradient (level 0)
#
# Every dot product is accumulated in float64 (``sc`` is always an f64 field and
# each term is widened before the add): a float32 sum of ~10^6 terms carries a
# relative error of order 1e-3..1e-2, which made alpha/beta inconsistent with
# the vectors and stalled float32 CG near 1e-5 at 1024^2.


@ti.func
def _sq(v):
    d = ti.cast(v, ti.f64)
    return d * d


@ti.func
def _mul(a, b):
    return ti.cast(a, ti.f64) * ti.cast(b, ti.f64)



@ti.func
def _residual_point(x: ti.template(), b: ti.template(), wx: ti.template(), wy: ti.template(), dg: ti.template(),
                    i, j, h, w):
    """(b - A x) at level-0 pixel (i, j); 0 outside the mask."""
    d = dg[i, j]
    v = b[i, j] * 0
    if d > 0:
        v = b[i, j] - d * x[i, j] + _neigh(x, wx, wy, i, j, 0, h, w)
    return v


@ti.func
def _start_point(x: ti.template(), b: ti.template(), r: ti.template(), e: ti.template(), f: ti.template(),
                 wx: ti.template(), wy: ti.template(), dg: ti.template(), i, j, h, w):
    """cg_start at (i, j): r = f = b - A x, e = 0; returns r^2 (float64)."""
    v = _residual_point(x, b, wx, wy, dg, i, j, h, w)
    r[i, j] = v
    f[i, j] = v
    e[i, j] = 0
    return _sq(v)


@ti.func
def _apply_point(p: ti.template(), q: ti.template(), wx: ti.template(), wy: ti.template(), dg: ti.template(),
                 i, j, h, w):
    """q = A p at (i, j); returns p q (float64)."""
    d = dg[i, j]
    v = p[i, j] * 0
    if d > 0:
        v = d * p[i, j] - _neigh(p, wx, wy, i, j, 0, h, w)
    q[i, j] = v
    return _mul(p[i, j], v)


@ti.func
def _update_point(x: ti.template(), r: ti.template(), p: ti.template(), q: ti.template(), e: ti.template(),
                  f: ti.template(), a, i, j):
    """x += a p, r -= a q, f = r, e = 0 at (i, j); returns the new r^2 (float64)."""
    x[i, j] += a * p[i, j]
    rv = r[i, j] - a * q[i, j]
    r[i, j] = rv
    f[i, j] = rv
    e[i, j] = 0
    return _sq(rv)


# Each kernel below has two builds, chosen by its last argument ``block`` (a compile-time constant):
# False: parallel loops with ``sc[K] +=`` (the CPU build: Taichi's CPU threads keep these sums
# thread-local; shared arrays do not exist there); True (CUDA only): the same per-pixel work in loops
# over h*w rounded up to whole blocks, (i, j) = (k // w, k % w), each sum tree-reduced per block in
# shared memory with one float64 atomic a block (:mod:`gpps.kernels.block_sum`).  On CUDA ``sc[K] +=``
# is one float64 atomic a pixel on one address: 117 us a loop on 43k mask pixels of a 256^2 map on an
# H100, where a pass over 65k pixels takes a few us.  The per-pixel arithmetic, the float64 terms and
# the alpha/beta rules are the same in both builds; only the order of the float64 additions differs.


@ti.kernel
def residual_norm(x: ti.template(), b: ti.template(), r: ti.template(), wx: ti.template(), wy: ti.template(),
                  dg: ti.template(), sc: ti.template(), h: ti.i32, w: ti.i32, block: ti.template()):
    """r = b - A x and sc[RR] = |r|^2."""
    sc[RR] = 0
    if ti.static(block):
        ti.loop_config(block_dim=BLOCK)
        for k in range(whole_blocks(h * w)):
            pad = ti.simt.block.SharedArray((BLOCK,), ti.f64)
            s = ti.cast(0, ti.f64)
            if k < h * w:
                i, j = k // w, k % w
                v = _residual_point(x, b, wx, wy, dg, i, j, h, w)
                r[i, j] = v
                s = _sq(v)
            block_add(pad, k, s, sc, RR)
    else:
        for i, j in ti.ndrange(h, w):
            v = _residual_point(x, b, wx, wy, dg, i, j, h, w)
            r[i, j] = v
            sc[RR] += _sq(v)


@ti.func
def _cg_start(x: ti.template(), b: ti.template(), r: ti.template(), e: ti.template(), f: ti.template(),
              wx: ti.template(), wy: ti.template(), dg: ti.template(), sc: ti.template(), h: ti.template(),
              w: ti.template(), block: ti.template()):
    """r = b - A x, sc[RR] = |r|^2, and the preconditioner input f_0 = r, e_0 = 0."""
    sc[RR] = 0
    if ti.static(block):
        ti.loop_config(block_dim=BLOCK)
        for k in range(whole_blocks(h * w)):
            pad = ti.simt.block.SharedArray((BLOCK,), ti.f64)
            s = ti.cast(0, ti.f64)
            if k < h * w:
                s = _start_point(x, b, r, e, f, wx, wy, dg, k // w, k % w, h, w)
            block_add(pad, k, s, sc, RR)
    else:
        for i, j in ti.ndrange(h, w):
            sc[RR] += _start_point(x, b, r, e, f, wx, wy, dg, i, j, h, w)


@ti.func
def _cg_first_direction(r: ti.template(), e: ti.template(), p: ti.template(), sc: ti.template(), h: ti.template(),
                        w: ti.template(), block: ti.template()):
    """p = M r (already in e), sc[RZ] = r . M r."""
    sc[RZ] = 0
    if ti.static(block):
        ti.loop_config(block_dim=BLOCK)
        for k in range(whole_blocks(h * w)):
            pad = ti.simt.block.SharedArray((BLOCK,), ti.f64)
            s = ti.cast(0, ti.f64)
            if k < h * w:
                i, j = k // w, k % w
                p[i, j] = e[i, j]
                s = _mul(r[i, j], e[i, j])
            block_add(pad, k, s, sc, RZ)
    else:
        for i, j in ti.ndrange(h, w):
            p[i, j] = e[i, j]
            sc[RZ] += _mul(r[i, j], e[i, j])


@ti.func
def _cg_step(x: ti.template(), r: ti.template(), p: ti.template(), q: ti.template(), e: ti.template(),
             f: ti.template(), wx: ti.template(), wy: ti.template(), dg: ti.template(), sc: ti.template(),
             h: ti.template(), w: ti.template(), block: ti.template()):
    """q = A p; alpha = rz / p.q; x += alpha p; r -= alpha q; f_0 = r, e_0 = 0; sc[RR] = |r|^2."""
    sc[PQ] = 0
    if ti.static(block):
        ti.loop_config(block_dim=BLOCK)
        for k in range(whole_blocks(h * w)):
            pad = ti.simt.block.SharedArray((BLOCK,), ti.f64)
            s = ti.cast(0, ti.f64)
            if k < h * w:
                s = _apply_point(p, q, wx, wy, dg, k // w, k % w, h, w)
            block_add(pad, k, s, sc, PQ)
    else:
        for i, j in ti.ndrange(h, w):
            sc[PQ] += _apply_point(p, q, wx, wy, dg, i, j, h, w)
    sc[ALPHA] = 0
    if sc[PQ] > 0:
        sc[ALPHA] = sc[RZ] / sc[PQ]
    sc[RR] = 0
    if ti.static(block):
        ti.loop_config(block_dim=BLOCK)
        for k in range(whole_blocks(h * w)):
            pad = ti.simt.block.SharedArray((BLOCK,), ti.f64)
            s = ti.cast(0, ti.f64)
            if k < h * w:
                s = _update_point(x, r, p, q, e, f, ti.cast(sc[ALPHA], x.dtype), k // w, k % w)
            block_add(pad, k, s, sc, RR)
    else:
        for i, j in ti.ndrange(h, w):
            sc[RR] += _update_point(x, r, p, q, e, f, ti.cast(sc[ALPHA], x.dtype), i, j)


@ti.func
def _cg_direction(r: ti.template(), e: ti.template(), p: ti.template(), sc: ti.template(), h: ti.template(),
                  w: ti.template(), block: ti.template()):
    """rz' = r . M r; p = M r + (rz'/rz) p; rz = rz'."""
    sc[RZN] = 0
    if ti.static(block):
        ti.loop_config(block_dim=BLOCK)
        for k in range(whole_blocks(h * w)):
            pad = ti.simt.block.SharedArray((BLOCK,), ti.f64)
            s = ti.cast(0, ti.f64)
            if k < h * w:
                s = _mul(r[k // w, k % w], e[k // w, k % w])
            block_add(pad, k, s, sc, RZN)
    else:
        for i, j in ti.ndrange(h, w):
            sc[RZN] += _mul(r[i, j], e[i, j])
    beta = sc[RZN] * 0
    if sc[RZ] > 0:
        beta = sc[RZN] / sc[RZ]
    sc[RZ] = sc[RZN]
    bt = ti.cast(beta, p.dtype)
    for i, j in ti.ndrange(h, w):
        p[i, j] = e[i, j] + bt * p[i, j]


@ti.kernel
def cg_start(x: ti.template(), b: ti.template(), r: ti.template(), e: ti.template(), f: ti.template(),
             wx: ti.template(), wy: ti.template(), dg: ti.template(), sc: ti.template(), h: ti.i32, w: ti.i32,
             block: ti.template()):
    """r = b - A x, sc[RR] = |r|^2, and the preconditioner input f_0 = r, e_0 = 0 (:func:`_cg_start`)."""
    _cg_start(x, b, r, e, f, wx, wy, dg, sc, h, w, block)


@ti.kernel
def cg_first_direction(r: ti.template(), e: ti.template(), p: ti.template(), sc: ti.template(), h: ti.i32,
                       w: ti.i32, block: ti.template()):
    """p = M r (already in e), sc[RZ] = r . M r (:func:`_cg_first_direction`)."""
    _cg_first_direction(r, e, p, sc, h, w, block)


@ti.kernel
def cg_step(x: ti.template(), r: ti.template(), p: ti.template(), q: ti.template(), e: ti.template(),
            f: ti.template(), wx: ti.template(), wy: ti.template(), dg: ti.template(), sc: ti.template(),
            h: ti.i32, w: ti.i32, block: ti.template()):
    """q = A p; alpha = rz / p.q; x += alpha p; r -= alpha q; f_0 = r, e_0 = 0; sc[RR] = |r|^2 (:func:`_cg_step`)."""
    _cg_step(x, r, p, q, e, f, wx, wy, dg, sc, h, w, block)


@ti.kernel
def cg_direction(r: ti.template(), e: ti.template(), p: ti.template(), sc: ti.template(), h: ti.i32, w: ti.i32,
                 block: ti.template()):
    """rz' = r . M r; p = M r + (rz'/rz) p; rz = rz' (:func:`_cg_direction`)."""
    _cg_direction(r, e, p, sc, h, w, block)


# ----------------------------------------------------------------------------- fused PCG launches
#
# The kernels above launch one step each: a PCG iteration is cg_step, the V-cycle (down per level,
# coarse_exact, up per level) and cg_direction, ~13 Taichi launches, and Taichi 1.7 spends ~60-100 us
# of host time on each call (it re-derives every argument), more than the GPU spends on the iteration
# at 256^2.  The two kernels below compose the same ti.funcs into one launch: Taichi runs a kernel's
# top-level loops and serial statements as consecutive tasks with a global barrier between them, so
# the arithmetic and its order are those of the separate kernels.  The level geometry ``geom`` is a
# compile-time tuple ``((off, h, w), ...)`` per level, finest first (one compile per mask size), so the
# V-cycle unrolls with ``ti.static``.


@ti.func
def _vcycle(e: ti.template(), f: ti.template(), t: ti.template(), wx: ti.template(), wy: ti.template(),
            dg: ti.template(), cidx: ti.template(), pinv: ti.template(), nc: ti.template(), geom: ti.template(),
            omega: ti.template(), npairs: ti.template()):
    """One V-cycle e = M f at level 0: down per level, the coarsest level's exact solve, up per level."""
    for k in ti.static(range(len(geom) - 1)):
        _down(e, f, t, wx, wy, dg, ti.static(geom[k][0]), ti.static(geom[k][1]), ti.static(geom[k][2]),
              ti.static(geom[k + 1][0]), ti.static(geom[k + 1][1]), ti.static(geom[k + 1][2]), omega, npairs)
    _coarse_exact(e, f, cidx, pinv, nc)
    for k in ti.static(range(len(geom) - 2, -1, -1)):
        _up(e, f, t, wx, wy, dg, ti.static(geom[k][0]), ti.static(geom[k][1]), ti.static(geom[k][2]),
            ti.static(geom[k + 1][0]), omega, npairs)


@ti.kernel
def pcg_start(x: ti.template(), b: ti.template(), r: ti.template(), e: ti.template(), f: ti.template(),
              t: ti.template(), p: ti.template(), wx: ti.template(), wy: ti.template(), dg: ti.template(),
              sc: ti.template(), cidx: ti.template(), pinv: ti.template(), nc: ti.i32, geom: ti.template(),
              omega: ti.template(), npairs: ti.template(), block: ti.template()):
    """The PCG's start in one launch: :func:`_cg_start`, the first V-cycle, :func:`_cg_first_direction`.

    ``geom``: ((off, h, w), ...) per level, finest first (level 0 is the (h, w) image); ``nc``: active
    cells of the coarsest level (rows of ``pinv`` and ``cidx`` in use).
    """
    _cg_start(x, b, r, e, f, wx, wy, dg, sc, ti.static(geom[0][1]), ti.static(geom[0][2]), block)
    _vcycle(e, f, t, wx, wy, dg, cidx, pinv, nc, geom, omega, npairs)
    _cg_first_direction(r, e, p, sc, ti.static(geom[0][1]), ti.static(geom[0][2]), block)


@ti.kernel
def pcg_iteration(x: ti.template(), r: ti.template(), p: ti.template(), q: ti.template(), e: ti.template(),
                  f: ti.template(), t: ti.template(), wx: ti.template(), wy: ti.template(), dg: ti.template(),
                  sc: ti.template(), cidx: ti.template(), pinv: ti.template(), nc: ti.i32, geom: ti.template(),
                  omega: ti.template(), npairs: ti.template(), block: ti.template()):
    """One PCG iteration in one launch: :func:`_cg_step` (sc[RR] = |r|^2 for the host's check), the
    V-cycle, :func:`_cg_direction` (arguments as :func:`pcg_start`).  The V-cycle and the new direction
    touch neither ``x`` nor sc[RR], so stopping after this launch leaves the same solution as stopping
    after cg_step alone."""
    _cg_step(x, r, p, q, e, f, wx, wy, dg, sc, ti.static(geom[0][1]), ti.static(geom[0][2]), block)
    _vcycle(e, f, t, wx, wy, dg, cidx, pinv, nc, geom, omega, npairs)
    _cg_direction(r, e, p, sc, ti.static(geom[0][1]), ti.static(geom[0][2]), block)


# ----------------------------------------------------------------------------- right-hand side on the device


@ti.func
def pixel_steps(nrm: ti.template(), i, j, perspective, fx, fy, cx, cy, s, min_nz):
    """``(du/dj, du/di)`` at pixel (i, j) from its unit normal (float64).

    Orthographic: du/dj = s n_x / n_z, du/di = -s n_y / n_z.
    Perspective (PPN, (3.2)-(3.3)): with m = n . ((j-cx)/fx, -(i-cy)/fy, -1) < 0,
    d(log d)/dj = -n_x / (fx m), d(log d)/di = n_y / (fy m).
    """
    nx = ti.cast(nrm[i, j, 0], ti.f64)
    ny = ti.cast(nrm[i, j, 1], ti.f64)
    nz = ti.cast(nrm[i, j, 2], ti.f64)
    a = ti.cast(0, ti.f64)
    c = ti.cast(0, ti.f64)
    if perspective:
        m = ti.min(nx * (j - cx) / fx - ny * (i - cy) / fy - nz, -min_nz)
        a = -nx / (fx * m)
        c = ny / (fy * m)
    else:
        den = ti.max(nz, min_nz)
        a = s * nx / den
        c = -s * ny / den
    return a, c


@ti.func
def div_mean_steps(gj: ti.template(), gi: ti.template(), wx: ti.template(), wy: ti.template(), i, j, h, w):
    """-div at (i, j) of the edge targets t = mean of the two pixels' steps (weights wx, wy)."""
    v = gj[i, j] * 0
    if j > 0:
        v += wx[i, j - 1] * 0.5 * (gj[i, j - 1] + gj[i, j])
    if j < w - 1:
        v -= wx[i, j] * 0.5 * (gj[i, j] + gj[i, j + 1])
    if i > 0:
        v += wy[i - 1, j] * 0.5 * (gi[i - 1, j] + gi[i, j])
    if i < h - 1:
        v -= wy[i, j] * 0.5 * (gi[i, j] + gi[i + 1, j])
    return v


@ti.kernel
def gradients_uniform(nrm: ti.types.ndarray(), gj: ti.template(), gi: ti.template(), dg: ti.template(),
                      perspective: ti.i32, fx: ti.f64, fy: ti.f64, cx: ti.f64, cy: ti.f64, s: ti.f64,
                      min_nz: ti.f64, h: ti.i32, w: ti.i32):
    """Per-pixel steps of u (depth, or log-depth under perspective) from unit normals (:func:`pixel_steps`).

    ``nrm`` is any (H, W, 3) array Taichi accepts (numpy, or a CUDA torch tensor).
    """
    for i, j in ti.ndrange(h, w):
        a = ti.cast(0, ti.f64)
        c = ti.cast(0, ti.f64)
        if dg[i, j] > 0:
            a, c = pixel_steps(nrm, i, j, perspective, fx, fy, cx, cy, s, min_nz)
        gj[i, j] = ti.cast(a, gj.dtype)
        gi[i, j] = ti.cast(c, gi.dtype)


@ti.kernel
def rhs_uniform(gj: ti.template(), gi: ti.template(), wx: ti.template(), wy: ti.template(), b: ti.template(),
                h: ti.i32, w: ti.i32):
    """b = -div of the edge targets t = mean of the two pixels' steps (weights wx, wy)."""
    for i, j in ti.ndrange(h, w):
        b[i, j] = div_mean_steps(gj, gi, wx, wy, i, j, h, w)

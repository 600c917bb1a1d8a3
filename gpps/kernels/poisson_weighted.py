"""Taichi device math of the integrator's weighted system, assembled on the device (4.20).

:class:`gpps.pipeline.integration.Integrator` assembles its system on the host
(:func:`gpps.host.poisson.pixel_gradients`, :func:`gpps.host.poisson.edge_system`,
:func:`gpps.host.poisson.build_levels`, :func:`gpps.host.poisson.coarsest_pinv`).
These kernels build the same system from a normal map that is already on the
device (a solver's buffer), into the integrator's own fields, so that RON's
rounds exchange depth and normals without a host round trip
(:class:`gpps.pipeline.integration_rounds.DeviceSystem`):

* :func:`assemble_pixels`: the checks of ``Integrator._check_normals``
  (finite, non-zero, camera-facing) and the per-pixel steps and BiNI factors of
  ``pixel_gradients``; with ``"normal"`` weighting the confidences ``N_z^2``
  (their mean over the valid pixels, the host's ``scale``, is summed here);
* :func:`assemble_edges`: ``edge_system`` with ``w+ = 1/2`` (edge weight
  ``(c_a + c_b) / 2``, flux ``(c_a g_a + c_b g_b) / 2``), the right-hand side
  ``b = -div(w t)`` and the level-0 diagonal;
* :func:`coarsen`: one level of ``build_levels`` (2x2 aggregation, coarse edge
  weight ``alpha`` times the crossing fine weights) and its diagonal;
* :func:`assemble_targets`: per-pixel steps and confidences given directly (the depth refinement's
  increments, :mod:`gpps.kernels.depth_refine`) instead of from normals; :func:`depth_add`: a depth moved by
  the solved increment (``u + z - mean z`` per component);
* :func:`gather_level`: the coarsest level's edge weights into a small field: its
  exact pseudo-inverse (at most ``coarsest^2 = 64`` cells by default) is computed on
  the host by :func:`gpps.host.poisson.coarsest_pinv`, as for the host path (about 1 ms
  with one 1 KB read; the Gauss-Jordan elimination this replaced ran as one serial
  GPU task: 14.9 ms on an H100, perf/results/profile_256x3_H100_i);
* :func:`label_init`, :func:`label_hook`, :func:`label_compress`: the connected components
  (4-neighbourhood) of the valid pixels when some mask pixel's normal was dropped, by parallel
  hooking of roots along edges (``atomic_min``: a parent index is always smaller) and pointer
  jumping, repeated until no edge joins two roots (one flag read a pass); a component's label is
  its root pixel's flat index (the mask's own components, labelled once on the host, likewise);
* :func:`component_sums`, :func:`depth_exp`, :func:`depth_write`,
  :func:`depth_fill`: ``Integrator.fetch``'s post-processing (mean 0 per
  component, ``exp`` under perspective, mean depth ``reference`` per
  component) and RON's ``_fill_depth`` (dropped pixels filled by the mean
  depth), written into a float32 (H, W) array (the solver's depth buffer).

Float64 arithmetic for the assembly (as the host's numpy), cast to the field
precision where stored; sums in float64.  Only device code lives here.
"""

from gpps._taichi import ti

# indices into the float64 statistics field ``st``
C_SUM, N_VALID, N_INVALID, FILL_SUM, FILL_N, CHANGED, SPAN = 0, 1, 2, 3, 4, 5, 6


@ti.kernel
def assemble_pixels(nrm: ti.types.ndarray(), mask: ti.template(), gj: ti.template(), gi: ti.template(),
                    cj: ti.template(), ci: ti.template(), st: ti.template(), perspective: ti.i32, weighted: ti.i32,
                    fx: ti.f64, fy: ti.f64, cx: ti.f64, cy: ti.f64, s: ti.f64, min_nz: ti.f64, h: ti.i32, w: ti.i32):
    """Per-pixel steps ``gj, gi`` and confidences ``cj, ci`` (0: not valid) of the (H, W, 3) normals ``nrm``.

    Valid: inside ``mask`` (i32), finite, longer than 1e-6, facing the camera (the host's
    ``_check_normals``).  ``weighted``: ``cj = N_zj^2``, ``ci = N_zi^2`` (:func:`gpps.host.poisson.pixel_gradients`;
    divided by their mean later); else 1.  ``st[C_SUM]`` += ``cj``, ``st[N_VALID]``, ``st[N_INVALID]`` counted
    (``st`` zeroed by the caller).
    """
    for i, j in ti.ndrange(h, w):
        a = ti.cast(0, ti.f64)
        c = ti.cast(0, ti.f64)
        wj = ti.cast(0, ti.f64)
        wi = ti.cast(0, ti.f64)
        if mask[i, j] != 0:
            nx = ti.cast(nrm[i, j, 0], ti.f64)
            ny = ti.cast(nrm[i, j, 1], ti.f64)
            nz = ti.cast(nrm[i, j, 2], ti.f64)
            norm = ti.sqrt(nx * nx + ny * ny + nz * nz)
            ok = norm == norm and norm < 1e300 and norm > 1e-6
            facing = False
            if ok:
                nx, ny, nz = nx / norm, ny / norm, nz / norm
                if perspective:
                    facing = nx * (j - cx) / fx - ny * (i - cy) / fy - nz < 0
                else:
                    facing = nz > 0
            if ok and facing:
                nzj = ti.cast(0, ti.f64)
                nzi = ti.cast(0, ti.f64)
                if perspective:
                    m = ti.min(nx * (j - cx) / fx - ny * (i - cy) / fy - nz, -min_nz)
                    a = -nx / (fx * m)
                    c = ny / (fy * m)
                    nzj, nzi = -fx * m, -fy * m
                else:
                    den = ti.max(nz, min_nz)
                    a = s * nx / den
                    c = -s * ny / den
                    nzj = den / s
                    nzi = nzj
                wj, wi = ti.cast(1, ti.f64), ti.cast(1, ti.f64)
                if weighted:
                    wj, wi = nzj * nzj, nzi * nzi
                st[C_SUM] += wj
                st[N_VALID] += 1.0
            else:
                st[N_INVALID] += 1.0
        gj[i, j] = a
        gi[i, j] = c
        cj[i, j] = wj
        ci[i, j] = wi


@ti.kernel
def assemble_targets(steps: ti.types.ndarray(), conf: ti.types.ndarray(), mask: ti.template(), gj: ti.template(),
                     gi: ti.template(), cj: ti.template(), ci: ti.template(), st: ti.template(), h: ti.i32, w: ti.i32):
    """Per-pixel steps and confidences given directly (:mod:`gpps.kernels.depth_refine`'s targets): ``gj, gi``
    from ``steps`` (H, W, 2), ``cj, ci`` from ``conf`` (H, W, 2) inside ``mask`` (valid where both confidences are
    positive and finite, as :func:`assemble_pixels` counts them; ``st[C_SUM]`` sums ``cj``)."""
    for i, j in ti.ndrange(h, w):
        a = ti.cast(0, ti.f64)
        c = ti.cast(0, ti.f64)
        wj = ti.cast(0, ti.f64)
        wi = ti.cast(0, ti.f64)
        if mask[i, j] != 0:
            a0 = ti.cast(steps[i, j, 0], ti.f64)
            c0 = ti.cast(steps[i, j, 1], ti.f64)
            x = ti.cast(conf[i, j, 0], ti.f64)
            y = ti.cast(conf[i, j, 1], ti.f64)
            ok = x > 0 and y > 0 and x < 1e300 and y < 1e300 and a0 == a0 and c0 == c0
            if ok:
                a, c, wj, wi = a0, c0, x, y
                st[C_SUM] += wj
                st[N_VALID] += 1.0
            else:
                st[N_INVALID] += 1.0
        gj[i, j] = a
        gi[i, j] = c
        cj[i, j] = wj
        ci[i, j] = wi


@ti.kernel
def depth_add(z: ti.template(), cj: ti.template(), lab: ti.template(), csum: ti.template(), ccnt: ti.template(),
              base: ti.types.ndarray(), out: ti.types.ndarray(), perspective: ti.i32, h: ti.i32, w: ti.i32):
    """``out = base`` moved by the increment ``z`` (mean 0 per component, :func:`component_sums` first): ``u(out) =
    u(base) + z - mean z`` with ``u = log d`` (perspective) or ``d``, on the valid pixels (``cj > 0``); ``base``
    elsewhere."""
    for i, j in ti.ndrange(h, w):
        d = ti.cast(base[i, j], ti.f64)
        if cj[i, j] > 0 and lab[i, j] >= 0:
            l = lab[i, j]
            du = ti.cast(z[i, j], ti.f64) - csum[l] / ccnt[l]
            if perspective:
                d = d * ti.exp(du)
            else:
                d = d + du
        out[i, j] = ti.cast(d, ti.f32)


@ti.func
def _edge(ca, cb, ga, gb, sa, sb, inv):
    """(weight, flux) of the edge between pixels a and b with confidences ``ca, cb``, steps ``ga, gb`` and the shares
    ``sa, sb`` of their terms on this edge (1/2 each, or BiNI's ``w+`` / ``1 - w+``); 0 where either is not valid."""
    wgt = ti.cast(0, ti.f64)
    flx = ti.cast(0, ti.f64)
    a = ca * inv * sa
    b = cb * inv * sb
    if ca > 0 and cb > 0 and a + b > 0:
        wgt = a + b
        flx = wgt * ((a * ga + b * gb) / wgt)
    return wgt, flx


@ti.func
def _flux_j(gj: ti.template(), cj: ti.template(), i, j, inv):
    """(weight, flux) of the edge (i, j)-(i, j+1); 0 where either pixel is not valid."""
    return _edge(cj[i, j], cj[i, j + 1], gj[i, j], gj[i, j + 1], 0.5, 0.5, inv)


@ti.func
def _flux_i(gi: ti.template(), ci: ti.template(), i, j, inv):
    """(weight, flux) of the edge (i, j)-(i+1, j)."""
    return _edge(ci[i, j], ci[i + 1, j], gi[i, j], gi[i + 1, j], 0.5, 0.5, inv)


@ti.kernel
def assemble_edges(gj: ti.template(), gi: ti.template(), cj: ti.template(), ci: ti.template(), st: ti.template(),
                   weighted: ti.i32, wx: ti.template(), wy: ti.template(), dg: ti.template(), b: ti.template(),
                   h: ti.i32, w: ti.i32):
    """Level-0 edge weights ``wx, wy``, diagonal ``dg`` and right-hand side ``b = -div(w t)``
    (:func:`gpps.host.poisson.edge_system` with ``w+ = 1/2``, :func:`gpps.host.poisson.divergence_rhs`);
    with ``weighted`` the confidences are divided by their mean over the valid pixels (the host's ``scale``)."""
    inv = ti.cast(1, ti.f64)
    if weighted and st[N_VALID] > 0 and st[C_SUM] > 0:
        inv = st[N_VALID] / st[C_SUM]
    for i, j in ti.ndrange(h, w):
        ex = ti.cast(0, ti.f64)
        fx_ = ti.cast(0, ti.f64)
        ey = ti.cast(0, ti.f64)
        fy_ = ti.cast(0, ti.f64)
        d = ti.cast(0, ti.f64)
        rhs = ti.cast(0, ti.f64)
        if j < w - 1:
            ex, fx_ = _flux_j(gj, cj, i, j, inv)
        if i < h - 1:
            ey, fy_ = _flux_i(gi, ci, i, j, inv)
        d += ex + ey
        rhs -= fx_ + fy_
        if j > 0:
            e0, f0 = _flux_j(gj, cj, i, j - 1, inv)
            d += e0
            rhs += f0
        if i > 0:
            e1, f1 = _flux_i(gi, ci, i - 1, j, inv)
            d += e1
            rhs += f1
        wx[i, j] = ti.cast(ex, wx.dtype)
        wy[i, j] = ti.cast(ey, wy.dtype)
        dg[i, j] = ti.cast(d, dg.dtype)
        b[i, j] = ti.cast(rhs, b.dtype)


@ti.func
def _flux_j_split(gj: ti.template(), cj: ti.template(), wpl: ti.types.ndarray(), i, j, inv):
    """:func:`_flux_j` with the pixels' shares ``w+`` (forward) and ``1 - w+`` (backward) instead of 1/2 each."""
    return _edge(cj[i, j], cj[i, j + 1], gj[i, j], gj[i, j + 1], ti.cast(wpl[i, j, 0], ti.f64),
                 1.0 - ti.cast(wpl[i, j + 1, 0], ti.f64), inv)


@ti.func
def _flux_i_split(gi: ti.template(), ci: ti.template(), wpl: ti.types.ndarray(), i, j, inv):
    """:func:`_flux_i` with the pixels' shares (``wpl[..., 1]``)."""
    return _edge(ci[i, j], ci[i + 1, j], gi[i, j], gi[i + 1, j], ti.cast(wpl[i, j, 1], ti.f64),
                 1.0 - ti.cast(wpl[i + 1, j, 1], ti.f64), inv)


@ti.kernel
def assemble_edges_split(gj: ti.template(), gi: ti.template(), cj: ti.template(), ci: ti.template(),
                         wpl: ti.types.ndarray(), st: ti.template(), wx: ti.template(), wy: ti.template(),
                         dg: ti.template(), b: ti.template(), h: ti.i32, w: ti.i32):
    """:func:`assemble_edges` (weighted) with per-pixel forward shares ``wpl`` (H, W, 2) (BiNI's ``w+``; the host's
    :func:`gpps.host.poisson.edge_system` with ``wpj, wpi``): edge weight ``c_a w+_a + c_b (1 - w+_b)``."""
    inv = ti.cast(1, ti.f64)
    if st[N_VALID] > 0 and st[C_SUM] > 0:
        inv = st[N_VALID] / st[C_SUM]
    for i, j in ti.ndrange(h, w):
        ex = ti.cast(0, ti.f64)
        fx_ = ti.cast(0, ti.f64)
        ey = ti.cast(0, ti.f64)
        fy_ = ti.cast(0, ti.f64)
        d = ti.cast(0, ti.f64)
        rhs = ti.cast(0, ti.f64)
        if j < w - 1:
            ex, fx_ = _flux_j_split(gj, cj, wpl, i, j, inv)
        if i < h - 1:
            ey, fy_ = _flux_i_split(gi, ci, wpl, i, j, inv)
        d += ex + ey
        rhs -= fx_ + fy_
        if j > 0:
            e0, f0 = _flux_j_split(gj, cj, wpl, i, j - 1, inv)
            d += e0
            rhs += f0
        if i > 0:
            e1, f1 = _flux_i_split(gi, ci, wpl, i - 1, j, inv)
            d += e1
            rhs += f1
        wx[i, j] = ti.cast(ex, wx.dtype)
        wy[i, j] = ti.cast(ey, wy.dtype)
        dg[i, j] = ti.cast(d, dg.dtype)
        b[i, j] = ti.cast(rhs, b.dtype)


@ti.kernel
def coarsen(wx: ti.template(), wy: ti.template(), dg: ti.template(), off: ti.i32, h: ti.i32, w: ti.i32,
            offc: ti.i32, hc: ti.i32, wc: ti.i32, alpha: ti.f64):
    """The next level's edge weights and diagonal (:func:`gpps.host.poisson.build_levels`, one level):
    coarse cell (ci, cj) aggregates fine (2ci..2ci+1, 2cj..2cj+1); its j-edge weight is ``alpha`` times the
    fine j-edges leaving the block's right column, its i-edge weight those leaving its bottom row."""
    for ci_, cj_ in ti.ndrange(hc, wc):
        sx = ti.cast(0, ti.f64)
        sy = ti.cast(0, ti.f64)
        if cj_ < wc - 1:
            jj = 2 * cj_ + 1
            if jj < w:
                sx += ti.cast(wx[2 * ci_, off + jj], ti.f64)
                if 2 * ci_ + 1 < h:
                    sx += ti.cast(wx[2 * ci_ + 1, off + jj], ti.f64)
        if ci_ < hc - 1:
            ii = 2 * ci_ + 1
            if ii < h:
                sy += ti.cast(wy[ii, off + 2 * cj_], ti.f64)
                if 2 * cj_ + 1 < w:
                    sy += ti.cast(wy[ii, off + 2 * cj_ + 1], ti.f64)
        wx[ci_, offc + cj_] = ti.cast(alpha * sx, wx.dtype)
        wy[ci_, offc + cj_] = ti.cast(alpha * sy, wy.dtype)
    for ci_, cj_ in ti.ndrange(hc, wc):
        d = wx[ci_, offc + cj_] + wy[ci_, offc + cj_]
        if cj_ > 0:
            d += wx[ci_, offc + cj_ - 1]
        if ci_ > 0:
            d += wy[ci_ - 1, offc + cj_]
        dg[ci_, offc + cj_] = d


@ti.kernel
def gather_level(wx: ti.template(), wy: ti.template(), off: ti.i32, hc: ti.i32, wc: ti.i32, out: ti.template()):
    """The (hc, wc) level at packed column ``off`` of the edge weights into ``out[0 (wx) / 1 (wy), :hc, :wc]``
    (float64): the coarsest level, for its pseudo-inverse on the host."""
    for i, j in ti.ndrange(hc, wc):
        out[0, i, j] = ti.cast(wx[i, off + j], ti.f64)
        out[1, i, j] = ti.cast(wy[i, off + j], ti.f64)


@ti.kernel
def label_init(cj: ti.template(), lab: ti.template(), h: ti.i32, w: ti.i32):
    """Every valid pixel (``cj > 0``) its own root (its flat index); -1 elsewhere."""
    for i, j in ti.ndrange(h, w):
        lab[i, j] = i * w + j if cj[i, j] > 0 else -1


@ti.func
def _root(lab: ti.template(), k, w):
    r = k
    while lab[r // w, r % w] != r:
        r = lab[r // w, r % w]
    return r


@ti.kernel
def label_hook(lab: ti.template(), st: ti.template(), h: ti.i32, w: ti.i32):
    """Along each edge of valid pixels whose roots differ, the larger root's parent becomes at most the
    smaller one (``st[CHANGED]`` set, ``st`` zeroed there by the caller)."""
    for i, j in ti.ndrange(h, w):
        if lab[i, j] >= 0:
            for t in ti.static(range(2)):
                ii, jj = i + t, j + 1 - t
                if ii < h and jj < w and lab[ii, jj] >= 0:
                    a = _root(lab, i * w + j, w)
                    b = _root(lab, ii * w + jj, w)
                    if a != b:
                        hi, lo = ti.max(a, b), ti.min(a, b)
                        ti.atomic_min(lab[hi // w, hi % w], lo)
                        st[CHANGED] = 1.0


@ti.kernel
def label_compress(lab: ti.template(), h: ti.i32, w: ti.i32):
    """Pointer jumping: each valid pixel's label becomes its root."""
    for i, j in ti.ndrange(h, w):
        if lab[i, j] >= 0:
            lab[i, j] = _root(lab, i * w + j, w)


@ti.kernel
def component_sums(z: ti.template(), cj: ti.template(), lab: ti.template(), csum: ti.template(),
                   ccnt: ti.template(), cmax: ti.template(), cmin: ti.template(), st: ti.template(), h: ti.i32,
                   w: ti.i32):
    """Per component (``lab``, -1: none) of the valid pixels (``cj > 0``): the sum of ``z``, the count, the
    largest and smallest ``z``; ``st[SPAN]``: the largest ``max - min`` of a component."""
    for k in csum:
        csum[k] = 0.0
        ccnt[k] = 0.0
        cmax[k] = -1.0e300
        cmin[k] = 1.0e300
    for i, j in ti.ndrange(h, w):
        if cj[i, j] > 0 and lab[i, j] >= 0:
            v = ti.cast(z[i, j], ti.f64)
            csum[lab[i, j]] += v
            ccnt[lab[i, j]] += 1.0
            ti.atomic_max(cmax[lab[i, j]], v)
            ti.atomic_min(cmin[lab[i, j]], v)
    st[SPAN] = 0.0
    for k in cmax:  # (one atomic a component, not a pixel)
        if ccnt[k] > 0:
            ti.atomic_max(st[SPAN], cmax[k] - cmin[k])


@ti.kernel
def depth_exp(z: ti.template(), cj: ti.template(), lab: ti.template(), cmax: ti.template(), cden: ti.template(),
              h: ti.i32, w: ti.i32):
    """Perspective: the per-component sums of ``exp(z - max z)`` into ``cden`` (the depth before scaling, shifted
    by the component's largest log-depth: no overflow whatever its range; the scale to the reference cancels it)."""
    for k in cden:
        cden[k] = 0.0
    for i, j in ti.ndrange(h, w):
        if cj[i, j] > 0 and lab[i, j] >= 0:
            l = lab[i, j]
            cden[l] += ti.exp(ti.cast(z[i, j], ti.f64) - cmax[l])


@ti.kernel
def depth_write(z: ti.template(), cj: ti.template(), lab: ti.template(), csum: ti.template(), ccnt: ti.template(),
                cmax: ti.template(), cden: ti.template(), st: ti.template(), out: ti.types.ndarray(),
                perspective: ti.i32, ref: ti.f64, referenced: ti.i32, h: ti.i32, w: ti.i32):
    """The depth of the valid pixels into ``out`` (float32): ``u = z - mean z`` per component; perspective
    ``exp(u) * ref / mean exp(u)``, computed as ``exp(z - max z) * ref / mean exp(z - max z)`` (equal, and free
    of overflow), orthographic ``u + ref`` (``Integrator.fetch``); ``referenced`` 0: no reference, perspective
    ``exp(u)`` (``cden`` not read) and orthographic ``u + ref`` with ``ref`` 0 (``Integrator.fetch`` without one);
    ``st[FILL_SUM]``, ``st[FILL_N]``: their float32 values summed and counted (RON's fill value is their mean)."""
    st[FILL_SUM] = 0.0
    st[FILL_N] = 0.0
    for i, j in ti.ndrange(h, w):
        if cj[i, j] > 0 and lab[i, j] >= 0:
            l = lab[i, j]
            u = ti.cast(z[i, j], ti.f64) - csum[l] / ccnt[l]
            d = u + ref
            if perspective:
                if referenced:
                    d = ti.exp(ti.cast(z[i, j], ti.f64) - cmax[l]) * (ref / (cden[l] / ccnt[l]))
                else:
                    d = ti.exp(u)
            d32 = ti.cast(d, ti.f32)
            out[i, j] = d32
            st[FILL_SUM] += ti.cast(d32, ti.f64)
            st[FILL_N] += 1.0


@ti.kernel
def depth_fill(cj: ti.template(), lab: ti.template(), mask: ti.template(), st: ti.template(),
               out: ti.types.ndarray(), ref: ti.f64, outside: ti.f32, referenced: ti.i32, h: ti.i32, w: ti.i32):
    """RON's ``_fill_depth`` on ``out``: mask pixels that were dropped (or came out <= 0, with ``referenced``: an
    unreferenced orthographic depth has mean 0) get the mean depth of the valid ones (``ref`` when there are
    none); pixels outside the mask get ``outside``."""
    fill = ti.cast(ref, ti.f32)
    if st[FILL_N] > 0:
        fill = ti.cast(st[FILL_SUM] / st[FILL_N], ti.f32)
    for i, j in ti.ndrange(h, w):
        if mask[i, j] == 0:
            out[i, j] = outside
        elif not (cj[i, j] > 0 and lab[i, j] >= 0 and (out[i, j] > 0 or referenced == 0)):
            out[i, j] = fill

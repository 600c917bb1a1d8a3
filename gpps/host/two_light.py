"""A surface for pixels that see only two lights: the Lambertian ratio plus integrability (issue 25, cast shadows).

With three images a pixel in the cast shadow of one light keeps two lit observations.  The per-pixel fit cannot
tell a cast shadow from an attached one, so it tilts the normal until the dark observation is explained
(``n . l_k <= 0``): on a plane in the shadow of an object the normals come out tens of degrees off, and the depth
integrated from them, which RON's refinement starts from, carries the tilt.

Two lit observations still fix a direction in the normal's tangent plane.  With a Lambertian diffuse term
``I_kc = rho_c (n . l_k) E_kc`` the albedo cancels from the ratio of the two, leaving one linear equation per
channel in the unnormalised normal ``N`` (Onn and Bruckstein's two-image photometric stereo)::

    N . w_c = 0,    w_c = Y_2c l_1 - Y_1c l_2,    Y_kc = I_kc / E_kc

and ``N`` is affine in the gradient of the integrator's unknown ``u`` (log-depth under the perspective camera,
the seed's PPN (3.2)-(3.3); depth under the orthographic one): ``N = u_x a + u_y b + c``
(:func:`gpps.host.perspective.affine_normal`).  So each channel is one linear equation in ``u``'s
differences at the pixel: ``(a . w) u_x + (b . w) u_y = -(c . w)``, a first-order equation whose characteristics
carry ``u`` in from the pixels around the shadow.  :func:`two_light_log_depth` solves, in least squares over the
mask, these equations at the two-light pixels (four one-sided difference pairs each, which couple neighbours as
central differences would not, each row divided by ``|(a . w, b . w, c . w)|`` so that a nearly degenerate
equation weighs little), the integrator's Poisson rows ``u_q - u_p = (g_p + g_q) / 2`` on every edge with a
pixel of three or more lit observations (their per-pixel normals' gradients ``g`` with the integrator's slope
bound, :func:`gpps.host.poisson.pixel_gradients`; one-sided where the other pixel has fewer), and a small
second-difference term at the pixels with fewer than three lit observations (``smoothness``: the equations fix
``u`` along their characteristics only, and a characteristic that ends on the mask's border on both sides would
otherwise be free; a pixel with one lit observation or none has only this).

Which observations are dark: below ``relative`` (:data:`gpps.names.SHADOW_RELATIVE_MANY`, the same "dark: below 0.1
of the lit level" as the robust solver's) of the pixel's brightest ``Y``, dilated by one pixel (a shadow's edge
is a pixel wide: the footprint straddles it).  The ratio holds for a diffuse term: the
caller takes the model's specular part out of the images first (RON renders it at the per-pixel normals).  The
surface is a *start*, not a result: RON's refinement takes it from here and keeps it only where its likelihood
is the higher (:meth:`gpps.flows.ron.RON._refine`).  The equations hold in an attached shadow as well as in a cast
one; they are what the per-pixel fit lacks only in the cast one.

Directional lights (``directions`` (N, 3)), or per-pixel directions (N, H, W, 3) with ``images`` already divided
by the per-pixel radiance (near lights, linearised at a depth).  numpy / scipy (one sparse solve).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy import ndimage

from gpps._check import as_array, as_flags, as_mask, check_number
from gpps.camera import Orthographic, Perspective
from gpps.host.perspective import affine_normal
from gpps.host.poisson import pixel_gradients
from gpps.names import SHADOW_RELATIVE_MANY

__all__ = ["dark_observations", "two_light_log_depth", "SMOOTHNESS", "MIN_NZ", "MAX_PIXELS"]

#: weight of the second differences at the pixels with fewer than three lit observations, relative to the data rows'
#: 1 (small: it only removes the freedom along the characteristics that no lit pixel anchors)
SMOOTHNESS = 0.05
#: the integrator's default slope bound (``IntegratorConfig.min_nz``)
MIN_NZ = 1e-3
#: the most unknowns of the two-light sparse solve; a larger mask is solved on blocks (two_light_log_depth)
MAX_PIXELS = 1 << 17
#: the tiny Tikhonov term that fixes the constant of each connected part in the sparse solve
_TIKHONOV = 1e-8


def dark_observations(images, mask, valid=None, *, relative: float = SHADOW_RELATIVE_MANY, dilate: int = 1) -> np.ndarray:
    """The observations taken as shadowed: grey value below ``relative`` of the pixel's brightest.

    Args:
        images: (N, H, W, C) or (N, H, W) images over the lights' radiance (``Y``), >= 0.
        mask: (H, W) bool.
        valid: optional (N, H, W) bool observations to use (an invalid one counts as dark).
        relative: the fraction of the pixel's brightest grey value below which an observation is dark.
        dilate: grow each image's dark region by this many pixels (its edge pixels are part shadowed).

    Returns:
        (N, H, W) bool, False outside the mask.
    """
    y = np.asarray(images, dtype=np.float64)
    if y.ndim == 4:
        y = y.mean(-1)
    if y.ndim != 3:
        raise ValueError(f"images: expected (N, H, W[, C]), got shape {np.shape(images)}")
    m = as_mask("mask", mask, y.shape[1:])
    check_number("relative", relative, lo=0.0, hi=1.0)
    check_number("dilate", dilate, lo=0, integer=True)
    dark = y < relative * y.max(0)[None]
    if valid is not None:
        dark |= ~as_flags("valid", valid, y.shape)
    if dilate:
        dark = np.stack([ndimage.binary_dilation(d, iterations=int(dilate)) for d in dark])
    return dark & m[None]


def two_light_log_depth(images, dark, normals, mask, camera, directions, *, smoothness: float = SMOOTHNESS,
                        min_nz: float = MIN_NZ, max_pixels: int | None = MAX_PIXELS):
    """Least-squares ``u`` (log-depth, perspective; depth, orthographic) from the two-light equations and the
    per-pixel normals of the pixels with three or more lit observations (module docstring).

    Args:
        images: (N, H, W, C) or (N, H, W) images over the lights' radiance (``Y``).
        dark: (N, H, W) bool dark observations (:func:`dark_observations`).
        normals: (H, W, 3) per-pixel unit normals (used where three or more observations are lit).
        mask: (H, W) bool.
        camera: :class:`Orthographic` or :class:`Perspective`.
        directions: (N, 3) directional lights' unit directions, or (N, H, W, 3) per-pixel directions.
        smoothness: the second-difference weight at the pixels with fewer than three lit observations
            (:data:`SMOOTHNESS`).
        min_nz: the integrator's slope bound on the per-pixel normals' gradients
            (:func:`gpps.host.poisson.pixel_gradients`; ``IntegratorConfig.min_nz``).
        max_pixels: the most unknowns of the sparse solve (:data:`MAX_PIXELS`); a larger mask is solved on
            ``f x f`` blocks (the smallest integer ``f`` that fits: block means of the images and normals, a block
            dark where any of its pixels is, in the mask where all are; the camera's K divided accordingly) and
            ``u`` interpolated back (bilinear, the mask's other pixels from their nearest block): a start needs no
            finer surface, and the direct solve's time and memory grow faster than the pixels (512^2: 5.6 s and
            0.9 GB on the 2-core development machine).  None: no limit.

    Returns:
        ``(u, two)``: (H, W) float64 ``u`` with mean 0 over each connected part of the mask (0 outside), and the
        (H, W) bool two-light pixels; ``(None, two)`` when there are none.
    """
    y = np.asarray(images, dtype=np.float64)
    if y.ndim == 3:
        y = y[..., None]
    if y.ndim != 4:
        raise ValueError(f"images: expected (N, H, W[, C]), got shape {np.shape(images)}")
    n, h, w, nc = y.shape
    m = as_mask("mask", mask, (h, w))
    dk = as_flags("dark", dark, (n, h, w))
    nrm = as_array("normals", normals, shape=(h, w, 3), dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if d.shape not in ((n, 3), (n, h, w, 3)):
        raise ValueError(f"directions: expected ({n}, 3) or ({n}, {h}, {w}, 3), got {d.shape}")
    check_number("smoothness", smoothness, lo=0.0)
    p_all = int(m.sum())
    if max_pixels is not None and p_all > int(max_pixels):
        f = int(np.ceil(np.sqrt(p_all / float(max_pixels))))
        while int(_blocks(m, f, "all").sum()) > int(max_pixels):
            f += 1
        return _two_light_coarse(y, dk, nrm, m, camera, d, f, smoothness, min_nz)
    lit = ~dk
    nlit = lit.sum(0)
    two = m & (nlit == 2)
    many = m & (nlit >= 3)  # (a pixel with one lit observation or none has no row of its own)
    if not two.any():
        return None, two
    idx = np.full((h, w), -1, np.int64)
    idx[m] = np.arange(int(m.sum()))
    p = int(m.sum())
    rows, cols, vals, rhs = [], [], [], []
    neq = 0

    def add(r, c, v):
        rows.append(r)
        cols.append(c)
        vals.append(v)

    # Poisson rows on the edges with a pixel of >= 3 lit observations (the integrator's targets)
    gj, gi, _, _ = pixel_gradients(np.where(many[..., None], nrm, 0.0), many, camera, min_nz)
    g = np.stack([gj, gi], -1)
    for di, dj, comp in ((0, 1, 0), (1, 0, 1)):
        both = m[:h - di, :w - dj] & m[di:, dj:]
        t1, t2 = many[:h - di, :w - dj], many[di:, dj:]
        ii, jj = np.nonzero(both & (t1 | t2))
        g1, g2 = g[ii, jj, comp], g[ii + di, jj + dj, comp]
        a1, a2 = t1[ii, jj], t2[ii, jj]
        tgt = np.where(a1 & a2, 0.5 * (g1 + g2), np.where(a1, g1, g2))
        k = np.arange(ii.size) + neq
        add(k, idx[ii + di, jj + dj], np.ones(ii.size))
        add(k, idx[ii, jj], -np.ones(ii.size))
        rhs.append(tgt)
        neq += ii.size

    # the two-light rows: (a . w) u_x + (b . w) u_y = -(c . w), per channel, four one-sided difference pairs
    ii, jj = np.nonzero(two)
    order = np.argsort(dk[:, ii, jj], axis=0, kind="stable")  # lit (False) first
    k1, k2 = order[0], order[1]
    lo, hi = np.minimum(k1, k2), np.maximum(k1, k2)
    if d.ndim == 2:
        l1, l2 = d[lo], d[hi]
    else:
        l1, l2 = d[lo, ii, jj], d[hi, ii, jj]
    av, bv, cv = (x[ii, jj] for x in affine_normal(camera, (h, w)))
    for ch in range(nc):
        y1, y2 = y[lo, ii, jj, ch], y[hi, ii, jj, ch]
        wv = y2[:, None] * l1 - y1[:, None] * l2
        A, B, C = (np.sum(x * wv, -1) for x in (av, bv, cv))
        s = np.sqrt(A * A + B * B + C * C)
        ok = s > 0
        A, B, C = (np.where(ok, x / np.where(ok, s, 1.0), 0.0) for x in (A, B, C))
        for su in (1, -1):
            for sv in (1, -1):
                ju, iv = jj + su, ii + sv
                inside = ok & (ju >= 0) & (ju < w) & (iv >= 0) & (iv < h)
                inside[inside] &= m[ii[inside], ju[inside]] & m[iv[inside], jj[inside]]
                q = np.nonzero(inside)[0]
                if q.size == 0:
                    continue
                k = np.arange(q.size) + neq
                add(k, idx[ii[q], ju[q]], 0.5 * su * A[q])
                add(k, idx[iv[q], jj[q]], 0.5 * sv * B[q])
                add(k, idx[ii[q], jj[q]], -0.5 * (su * A[q] + sv * B[q]))
                rhs.append(-0.5 * C[q])
                neq += q.size

    # second differences at the pixels without a normal of their own (two lit observations or fewer)
    if smoothness > 0:
        few = m & ~many
        for di, dj in ((0, 1), (1, 0)):
            inner = np.zeros_like(m)
            inner[di:h - di, dj:w - dj] = few[di:h - di, dj:w - dj] & m[:h - 2 * di, :w - 2 * dj] & m[2 * di:, 2 * dj:]
            ii2, jj2 = np.nonzero(inner)
            k = np.arange(ii2.size) + neq
            s_ = float(smoothness)
            add(k, idx[ii2 - di, jj2 - dj], np.full(ii2.size, s_))
            add(k, idx[ii2, jj2], np.full(ii2.size, -2.0 * s_))
            add(k, idx[ii2 + di, jj2 + dj], np.full(ii2.size, s_))
            rhs.append(np.zeros(ii2.size))
            neq += ii2.size

    mat = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(neq, p))
    b = np.concatenate(rhs)
    ata = (mat.T @ mat + _TIKHONOV * sp.eye(p)).tocsc()
    u = spla.spsolve(ata, mat.T @ b)
    out = np.zeros((h, w))
    out[m] = u
    return _zero_mean_parts(out, m), two


def _blocks(a, f: int, how: str):
    """``a`` (H, W[, ...]) reduced over ``f x f`` blocks (padded at the far edges): "all", "any" (bool) or
    "sum"."""
    h, w = a.shape[:2]
    hc, wc = -(-h // f), -(-w // f)
    pad = [(0, hc * f - h), (0, wc * f - w)] + [(0, 0)] * (a.ndim - 2)
    fill = True if how == "all" else 0
    b = np.pad(a, pad, constant_values=fill).reshape((hc, f, wc, f) + a.shape[2:])
    return {"all": b.all, "any": b.any, "sum": b.sum}[how](axis=(1, 3))


def _two_light_coarse(y, dk, nrm, m, camera, d, f, smoothness, min_nz):
    """:func:`two_light_log_depth` on ``f x f`` blocks, ``u`` interpolated back to the pixels (its docstring)."""
    h, w = m.shape
    mc = _blocks(m, f, "all")
    cnt = np.maximum(_blocks(m.astype(np.float64), f, "sum"), 1.0)
    wm = m.astype(np.float64)
    yc = np.stack([_blocks(yk * wm[..., None], f, "sum") / cnt[..., None] for yk in y])
    dc = np.stack([_blocks(dk_ & m, f, "any") for dk_ in dk]) & mc[None]
    nc = _blocks(nrm * wm[..., None], f, "sum")
    nc = nc / np.maximum(np.linalg.norm(nc, axis=-1, keepdims=True), 1e-12)
    if d.ndim == 4:
        dd = np.stack([_blocks(dk_ * wm[..., None], f, "sum") for dk_ in d])
        dd = dd / np.maximum(np.linalg.norm(dd, axis=-1, keepdims=True), 1e-12)
    else:
        dd = d
    if isinstance(camera, Orthographic):
        cam_c = Orthographic(float(camera.pixel_size) * f)
    else:
        cx, cy = camera.principal_point()
        cam_c = Perspective([[camera.fx / f, 0.0, (cx - (f - 1) / 2) / f],
                             [0.0, camera.fy / f, (cy - (f - 1) / 2) / f], [0.0, 0.0, 1.0]])
    uc, twoc = two_light_log_depth(yc, dc, nc, mc, cam_c, dd, smoothness=smoothness, min_nz=min_nz, max_pixels=None)
    two = np.repeat(np.repeat(twoc, f, 0), f, 1)[:h, :w] & m
    if uc is None:
        return None, two
    # every coarse cell from its nearest block in the mask, then bilinear at the pixels' centres
    near = ndimage.distance_transform_edt(~mc, return_distances=False, return_indices=True)
    full = uc[near[0], near[1]]
    ic = (np.arange(h) - (f - 1) / 2.0) / f
    jc = (np.arange(w) - (f - 1) / 2.0) / f
    i0 = np.clip(np.floor(ic).astype(int), 0, mc.shape[0] - 1)
    j0 = np.clip(np.floor(jc).astype(int), 0, mc.shape[1] - 1)
    i1 = np.minimum(i0 + 1, mc.shape[0] - 1)
    j1 = np.minimum(j0 + 1, mc.shape[1] - 1)
    ti = np.clip(ic - i0, 0.0, 1.0)[:, None]
    tj = np.clip(jc - j0, 0.0, 1.0)[None, :]
    u = ((1 - ti) * (1 - tj) * full[np.ix_(i0, j0)] + (1 - ti) * tj * full[np.ix_(i0, j1)]
         + ti * (1 - tj) * full[np.ix_(i1, j0)] + ti * tj * full[np.ix_(i1, j1)])
    return _zero_mean_parts(u, m), two


def _zero_mean_parts(u, m) -> np.ndarray:
    """``u`` with mean 0 over each 4-connected part of the mask ``m`` (the integrator's parts), 0 outside."""
    lab, n = ndimage.label(m)
    means = np.bincount(lab[m], weights=u[m], minlength=n + 1) / np.maximum(np.bincount(lab[m], minlength=n + 1), 1)
    return np.where(m, u - means[lab], 0.0)

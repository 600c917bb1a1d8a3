"""Host algorithms of the single-image flow (seed ch. 6): image scaling, light estimation from normals,
the bas-relief from highlights, and the three-image normal starts.  numpy / scipy only; the flow is
:func:`gpps.flows.single.reconstruct_single`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from gpps._check import as_images, as_mask, check_number, clipping, warn
from gpps.host.gbr import integrability_gbr


def prepare_images(images, mask=None) -> tuple[np.ndarray, np.ndarray]:
    """``(images (N, H, W, 3) float32 scaled by one common 99th percentile, mask (H, W) bool)``.

    ``images``: one (H, W) / (H, W, 3) image, or a sequence / array of N of them.
    """
    if isinstance(images, (list, tuple)):
        items = [as_images(f"images[{k}]", i) for k, i in enumerate(images)]
        items = [i[..., None] if i.ndim == 2 else i for i in items]
        if not items or any(i.ndim != 3 or i.shape != items[0].shape for i in items):
            raise ValueError(f"images: expected (H, W) or (H, W, 3) images of one shape, got {[i.shape for i in items]}")
        a = np.stack(items)
    else:
        a = as_images("images", images)
        if a.ndim == 2:
            a = a[None, ..., None]
        elif a.ndim == 3:  # one RGB image (H, W, 3), else N grey images (N, H, W)
            if a.shape[-1] in (2, 4):
                # (read as N = H grey images 2 or 4 pixels wide before: an RGBA or grey-alpha image)
                raise ValueError(f"images: expected (H, W), (H, W, 3) or N of them, got shape {a.shape}: an image "
                                 f"with an alpha channel? Pass its colour channels (images[..., :3] or [..., 0]) and "
                                 f"the alpha as the mask; N grey images {a.shape[2]} pixels wide are too small")
            a = a[None] if a.shape[-1] == 3 else a[..., None]
    if a.ndim != 4 or a.shape[-1] not in (1, 3):
        raise ValueError(f"images: expected (H, W), (H, W, 3) or N of them, got shape {np.shape(images)}")
    if 0 in a.shape[:3]:
        raise ValueError(f"images: expected at least one image of at least 1 x 1 pixels, got shape {np.shape(images)}")
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, -1)
    a = np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0)
    a = np.maximum(a, 0.0)
    h, w = a.shape[1:3]
    # (as_mask: NaN or strings are an error, not True; emptiness is the lit-pixel check's below)
    m = np.ones((h, w), bool) if mask is None else as_mask("mask", mask, (h, w), allow_empty=True)
    m = m & (a.max(axis=(0, 3)) > 0)
    if m.sum() < 16:
        raise ValueError(f"mask: expected at least 16 lit object pixels, got {int(m.sum())}")
    _check_clipping(a, m)
    peak = a[:, m].max(-1)
    p = float(np.percentile(peak, 99.0))
    p = p if p > 0 else float(peak.max())  # (> 0: every mask pixel is lit in some image; any positive scale)
    return (a / np.float32(p)).astype(np.float32), m


def _check_clipping(a, m) -> None:
    """The images' clipping, as the calibrated flows check it (:func:`gpps._check.clipping`): the object's
    observations whose brightest channel sits at the full scale (1 for integer images, which arrive scaled; a raw
    level for floats).  90 % or more: a ValueError (everything saturated: no shading to read); 5 % or more: a
    warning."""
    verdict, top, share = clipping(a[:, m].max(-1))
    if verdict == "saturated":
        raise ValueError(f"images: {100 * share:.0f}% of the object's observations are at {top:g}, the full scale: "
                         "everything is saturated (over-exposed), there is no shading to read")
    if verdict == "clipped":
        warn(f"images: {100 * share:.1f}% of the object's observations sit at {top:g}, the full scale: clipped "
             "(saturated) highlights or over-exposure; the network and the search read them as they are")


def view_dirs(camera, shape, mask):
    if camera is None or not getattr(camera, "is_perspective", False):
        v = np.zeros((int(mask.sum()), 3), np.float32)
        v[:, 2] = 1.0
        return v
    _, d = camera.rays(shape)
    return (-d[mask]).astype(np.float32)


def _bp_spec(n, l, v, shininess):
    h = l[None] + v
    h /= np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    c = np.sum(n * h, -1)
    return np.where((c > 0) & (np.sum(n * l, -1) > 0), np.maximum(c, 0.0) ** shininess, 0.0)


def estimate_lights(I, n, view, *, albedo=None, shininess=30.0, specular=True, iterations=30):
    """Lights, albedo and ks from images and normals (the uncalibrated step of each round).

    Args:
        I: (N, P, 3) intensities of P pixels.
        n: (P, 3) unit normals.
        view: (P, 3) unit view directions.
        albedo: (P, 3) start albedo (None: ones).

    Returns:
        (directions (N, 3), intensities (N, 3), albedo (P, 3), ks): the mean intensity is
        kept at 1 (the scale is shared with the albedo).
    """
    I = np.asarray(I, np.float64)
    n = np.asarray(n, np.float64)
    nl, npx = I.shape[0], I.shape[1]
    kd = np.ones((npx, 3)) if albedo is None else np.maximum(np.asarray(albedo, np.float64), 1e-3)
    dirs = np.tile([0.0, 0.0, 1.0], (nl, 1))
    rgb = np.ones((nl, 3))
    bright = np.zeros((nl, npx), bool)
    for k in range(nl):
        g = I[k].sum(-1)
        bright[k] = g > np.quantile(g, 0.98)
    for it in range(iterations):
        for k in range(nl):
            Lc = np.zeros((3, 3))
            for c in range(3):
                ok = ~bright[k] & (I[k, :, c] > 1e-4) if it == 0 else ~bright[k] & (n @ dirs[k] > 0.05)
                if ok.sum() < 10:
                    ok = ~bright[k]
                A = kd[ok, c, None] * n[ok]
                Lc[c] = np.linalg.lstsq(A, I[k, ok, c], rcond=None)[0]
            s = Lc.sum(0)
            if np.linalg.norm(s) < 1e-12:
                continue
            dirs[k] = s / np.linalg.norm(s)
            rgb[k] = np.maximum(Lc @ dirs[k], 1e-6)
        shade = np.maximum(n @ dirs.T, 0.0)  # (P, N)
        num = np.einsum("pk,kpc,kc->pc", shade, I, rgb)
        den = np.einsum("pk,kc->pc", shade**2, rgb**2)
        kd = np.where(den > 1e-12, np.maximum(num / np.maximum(den, 1e-12), 0.0), kd)
        scale = rgb.mean()
        rgb /= scale
        kd *= scale
    ks = 0.0
    if specular:
        v = np.asarray(view, np.float64)
        num = den = 0.0
        for k in range(nl):
            s = _bp_spec(n, dirs[k], v, shininess)  # (P,)
            r = I[k] - rgb[k] * kd * np.maximum(n @ dirs[k], 0.0)[:, None]
            es = rgb[k][None] * s[:, None]
            num += float(np.sum(r * es))
            den += float(np.sum(es * es))
        ks = float(np.clip(num / den, 0.0, 2.0)) if den > 1e-12 else 0.0
    return dirs.astype(np.float32), rgb.astype(np.float32), kd.astype(np.float32), ks


@dataclass
class HighlightFit:
    """What :func:`fit_highlights` found.

    Attributes:
        gbr: (3, 3) the bas-relief ``G = [[1, 0, 0], [0, 1, 0], [mu, nu, lam]]`` (identity when rejected).
        directions: (N, 3) unit light directions ``G l / |G l|``.
        intensities: (N, 3) RGB intensities ``E |G l|``, rescaled to mean 1.
        normals: (P, 3) unit normals ``G^-T n / |G^-T n|``.
        albedo: (P, 3) albedo that keeps the Lambertian part of every image unchanged.
        ks: specular weight (0 when rejected).
        shininess: Blinn-Phong exponent.
        accepted: the highlights were seen and explain the images (see :func:`fit_highlights`).
        info: the numbers of the fit (``lam``, ``mu``, ``nu``, ``ks``, ``shininess``, ``accepted``,
            ``evidence`` (BIC gain), ``sse_ratio`` (residual after / before the lobe), ``normal_change_rms_deg``,
            ``peak`` (per light, the largest lobe value ``max_p s``)).
    """

    gbr: np.ndarray
    directions: np.ndarray
    intensities: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    ks: float
    shininess: float
    accepted: bool
    info: dict


def _gbr(theta) -> np.ndarray:
    return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [theta[1], theta[2], np.exp(theta[0])]])


def fit_highlights(I, n, view, directions, intensities, albedo, *, prior_deg: float = 10.0, shininess: float = 30.0,
                   shininess_range=(5.0, 300.0), max_pixels: int = 16384) -> HighlightFit:
    """The lights' generalized bas-relief, ``ks`` and ``shininess`` from the specular highlights.

    Lambertian shading cannot tell normals ``n`` and lights ``l`` from ``G^-T n`` and ``G l``
    for any bas-relief ``G = [[1, 0, 0], [0, 1, 0], [mu, nu, lam]]`` (Belhumeur, Kriegman
    and Yuille 1999: ``(G^-T n).(G l) = n.l``, attached shadows kept), so lights fitted
    to a prior's normals by least squares (:func:`estimate_lights`) inherit the prior's bias
    along that family (on the 256^2 Blinn-Phong sphere of ``perf/single_image.py`` the
    network's slants are 3-14 deg too small and the lights come out 9-11 deg too oblique,
    after which the refinement fits the flattened shape and ends worse than the network).  The
    specular lobe peaks where ``n = h = (l + v) / |l + v|``, which ``G`` moves, so the
    highlights fix ``G`` (Drbohlav and Sara 2002; Georghiades 2003).

    The estimate maximises the posterior with Gaussian residuals of unknown variance and
    the prior ``angle(G^-T n, n) ~ N(0, prior_deg^2)`` per pixel:
    ``(M / 2) log SSE(G, ks, s) + sum_p angle_p^2 / (2 prior_deg^2)``, ``M`` the lit
    observations, ``SSE`` the squared residual of the Lambertian model (unchanged by
    ``G``) minus the lobe ``E'_k ks max(n'.h'_k, 0)^s``.  ``ks`` is solved in closed form,
    at most what the brightest observation allows (``ks E'_k max_p s_kp <= max_p I_kp``);
    ``(log lam, mu, nu, log s)`` by Nelder-Mead from the identity and the best ``s`` of a
    grid.  The fit is *accepted* when every light's lobe reaches half its peak on some
    pixel (``max_p s_kp >= 1/2``; a lobe fitted by its tail alone explains shading
    errors, not a highlight) and the lobe with ``G`` (5 parameters) beats the Lambertian
    model alone by the Bayesian information criterion (``evidence > 0``; noise alone
    fits a small lobe too).  Rejected: ``G = I``, ``ks = 0``, the given ``shininess``.

    Args:
        I: (N, P, 3) intensities; n: (P, 3) unit normals the lights were fitted to;
        view: (P, 3) unit view directions; directions, intensities: (N, 3) lights;
        albedo: (P, 3) albedo (the Lambertian part is ``E_k albedo max(n.l_k, 0)``).
        prior_deg: spread of the normals' prior (deg), e.g. the network's validation MAEN.
        shininess: start (and the exponent returned when rejected).
        shininess_range: bounds ``(lo, hi)`` of the exponent.
        max_pixels: the fit uses every k-th pixel to at most this many (the output covers all).

    Raises:
        ValueError: inconsistent shapes or a bad setting, naming the argument.
    """
    I = np.asarray(I, np.float64)
    n = np.asarray(n, np.float64)
    view = np.asarray(view, np.float64)
    dirs = np.asarray(directions, np.float64)
    rgb = np.asarray(intensities, np.float64)
    kd = np.asarray(albedo, np.float64)
    if I.ndim != 3 or I.shape[-1] != 3:
        raise ValueError(f"I: expected shape (N, P, 3), got {I.shape}")
    nl, npx = I.shape[:2]
    for name, a, shape in (("n", n, (npx, 3)), ("view", view, (npx, 3)), ("directions", dirs, (nl, 3)),
                           ("intensities", rgb, (nl, 3)), ("albedo", kd, (npx, 3))):
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    prior_deg = check_number("prior_deg", prior_deg, lo=0.0, lo_open=True, hi=90.0)
    shininess = check_number("shininess", shininess, lo=0.0, lo_open=True)
    if len(shininess_range) != 2:
        raise ValueError(f"shininess_range: expected (lo, hi), got {shininess_range!r}")
    s_lo = check_number("shininess_range", shininess_range[0], lo=0.0, lo_open=True)
    s_hi = check_number("shininess_range", shininess_range[1], lo=s_lo)
    max_pixels = check_number("max_pixels", max_pixels, lo=1, integer=True)

    sel = np.arange(0, npx, max(1, -(-npx // max_pixels)))
    Is, ns, vs = I[:, sel], n[sel], view[sel]
    shade = np.maximum(ns @ dirs.T, 0.0).T  # (N, Ps)
    r = Is - rgb[:, None, :] * kd[sel][None] * shade[:, :, None]  # Lambertian residual, the same for every G
    m_obs = max(3 * int(np.count_nonzero(shade > 0)), 1)
    i_max = Is.max(axis=(1, 2))
    sig2 = np.radians(prior_deg) ** 2

    def model(theta):
        G = _gbr(theta)
        sh = float(np.clip(np.exp(theta[3]), s_lo, s_hi))
        b = ns @ np.linalg.inv(G)  # rows G^-T n
        n2 = b / np.linalg.norm(b, axis=1, keepdims=True)
        gl = dirs @ G.T
        gn = np.linalg.norm(gl, axis=1)
        l2 = gl / gn[:, None]
        e2 = rgb * gn[:, None]
        e2 /= e2.mean()
        lobe = np.zeros(shade.shape)
        for k in range(nl):
            h = l2[k][None] + vs
            h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
            c = np.sum(n2 * h, 1)
            lobe[k] = np.where((c > 0) & (shade[k] > 0), np.maximum(c, 1e-30) ** sh, 0.0)
        es = e2[:, None, :] * lobe[:, :, None]
        den = float(np.sum(es * es))
        ks = max(float(np.sum(es * r)) / den, 0.0) if den > 1e-20 else 0.0
        peak = lobe.max(1)
        ks = min(ks, float(np.min(i_max / np.maximum(e2.max(1) * peak, 1e-12))))
        sse = float(np.sum((r - ks * es) ** 2))
        ang2 = float(np.sum(np.arccos(np.clip(np.sum(n2 * ns, 1), -1.0, 1.0)) ** 2))
        return sse, ang2, ks, sh, peak

    def objective(theta):
        sse, ang2 = model(theta)[:2]
        return 0.5 * m_obs * np.log(max(sse, 1e-300)) + ang2 / (2.0 * sig2)

    grid = np.unique(np.append(np.geomspace(s_lo, s_hi, 9), np.clip(shininess, s_lo, s_hi)))
    j0 = [objective(np.array([0.0, 0.0, 0.0, np.log(g)])) for g in grid]
    t0 = np.array([0.0, 0.0, 0.0, np.log(grid[int(np.argmin(j0))])])
    opt = minimize(objective, t0, method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-3, "maxiter": 800})
    theta = opt.x if opt.fun <= objective(t0) else t0
    sse, ang2, ks, sh, peak = model(theta)
    sse0 = float(np.sum(r * r))
    # BIC of the lobe and the bas-relief (5 parameters) against the Lambertian model alone
    evidence = 0.5 * m_obs * np.log(max(sse0, 1e-300) / max(sse, 1e-300)) - 2.5 * np.log(m_obs)
    accepted = bool(ks > 0.0 and evidence > 0.0 and np.all(peak >= 0.5))
    info = {"lam": float(np.exp(theta[0])), "mu": float(theta[1]), "nu": float(theta[2]), "ks": float(ks),
            "shininess": sh, "accepted": accepted, "evidence": float(evidence), "sse_ratio": sse / max(sse0, 1e-300),
            "normal_change_rms_deg": float(np.degrees(np.sqrt(ang2 / len(sel)))), "peak": peak.tolist()}
    if not accepted:
        return HighlightFit(np.eye(3), dirs.astype(np.float32), rgb.astype(np.float32), n.astype(np.float32),
                            kd.astype(np.float32), 0.0, float(shininess), False, info)
    G = _gbr(theta)
    b = n @ np.linalg.inv(G)
    bn = np.linalg.norm(b, axis=1, keepdims=True)
    gl = dirs @ G.T
    gn = np.linalg.norm(gl, axis=1)
    e2 = rgb * gn[:, None]
    scale = e2.mean()
    return HighlightFit(G, (gl / gn[:, None]).astype(np.float32), (e2 / scale).astype(np.float32),
                        (b / bn).astype(np.float32), (kd * bn * scale).astype(np.float32), float(ks), sh, True, info)


def explained_fraction(I, n, view, directions, intensities, albedo, ks: float, shininess: float) -> np.ndarray:
    """Per pixel, the share of its observations' energy the Blinn-Phong image model explains:
    ``1 - sum_k |I_k - E_k (kd max(n.l_k, 0) + ks s_k)|^2 / sum_k |I_k|^2`` (the model of
    :func:`gpps.kernels.cuckoo.photometric_error`, without the prior term).

    Args:
        I: (N, P, 3) observations; n: (P, 3) unit normals; view: (P, 3) view directions.
        directions, intensities: (N, 3) lights; albedo: (P, 3); ks, shininess: the specular lobe.

    Returns:
        (P,) float64, at most 1; negative where the model is farther from the observations than zero is
        (a cast shadow the model lights, a light estimate that failed); 0 for a black pixel.
    """
    I = np.asarray(I, np.float64)
    n = np.asarray(n, np.float64)
    res = np.zeros(I.shape[1])
    for k in range(I.shape[0]):
        a = np.maximum(n @ directions[k], 0.0)
        s = ks * _bp_spec(n, directions[k], view, shininess) if ks > 0 else 0.0
        model = intensities[k] * (albedo * a[:, None] + (s * np.ones(1))[..., None] * (a > 0)[:, None])
        res += np.sum((I[k] - model) ** 2, -1)
    energy = np.sum(I**2, axis=(0, 2))
    return np.where(energy > 0, 1.0 - res / np.maximum(energy, 1e-300), 0.0)


def factorization_normals(I, prior, *, irls: int = 3, shadow: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Uncalibrated Lambertian normals from N >= 3 images, their linear ambiguity fixed by a prior.

    The grey intensities ``M`` (P, N) are factorised to rank 3, ``M ~ B0 S0`` (SVD); any
    ``B = B0 A``, ``S = A^-1 S0`` fits as well.  ``A`` (3 x 3, up to scale) is the one that
    makes ``B`` most parallel to the ``prior`` normals: the smallest eigenvector of
    ``sum_p w_p G_p^T (I - n_p n_p^T) G_p`` (``G_p a = B0_p A``), re-weighted ``irls`` times by
    ``w = 1 / (1 + (angle / 15 deg)^2)``.  Pixels in shadow in any image (below ``shadow`` x
    the image's 99th percentile) or among an image's brightest 2 % get no weight.

    Returns:
        (normals (P, 3), lights (N, 3) = intensity x direction, grey).
    """
    g = np.asarray(I, np.float64).sum(-1)  # (N, P)
    n = np.asarray(prior, np.float64)
    nl, npx = g.shape
    if nl < 3:
        raise ValueError(f"images: the factorisation needs at least 3 images, got {nl}")
    U, sv, Vt = np.linalg.svd(g.T, full_matrices=False)
    B0 = U[:, :3] * np.sqrt(sv[:3])
    S0 = np.sqrt(sv[:3])[:, None] * Vt[:3]
    ok = np.ones(npx, bool)
    for k in range(nl):
        q99 = np.quantile(g[k], 0.99)
        ok &= (g[k] > shadow * q99) & (g[k] < np.quantile(g[k], 0.98))
    if ok.sum() < 20:
        ok = np.ones(npx, bool)
    w = ok.astype(np.float64)
    G = np.zeros((npx, 3, 9))
    for i in range(3):
        for j in range(3):
            G[:, j, 3 * i + j] = B0[:, i]
    Pp = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
    for _ in range(irls + 1):
        Q = np.einsum("p,pji,pjk,pkl->il", w, G, Pp, G)
        a = np.linalg.eigh(Q)[1][:, 0]
        A = a.reshape(3, 3)
        B = B0 @ A
        if np.sum(w * np.sum(B * n, 1)) < 0:
            A, B = -A, -B
        Bn = B / np.maximum(np.linalg.norm(B, axis=1, keepdims=True), 1e-12)
        ang = np.degrees(np.arccos(np.clip(np.sum(Bn * n, 1), -1, 1)))
        w = ok / (1.0 + (ang / 15.0) ** 2)
    S = np.linalg.solve(A, S0)  # (3, N)
    return Bn.astype(np.float32), S.T.astype(np.float32)


def integrable_normals(I, prior, mask, *, smooth: float = 1.0, irls: int = 2):
    """Uncalibrated Lambertian normals from N >= 3 images: factorisation, integrability, GBR from a prior.

    Rank-3 factorisation of the grey intensities, the 3x3 ambiguity reduced to a GBR by
    integrability (:func:`gpps.host.gbr.integrability_gbr`), and the GBR
    ``b -> (b_x + a b_z, b_y + c b_z, d b_z)`` fitted to the ``prior`` normals by robust least
    squares (three parameters, linear; Cauchy-like weights at 15 deg).

    Args:
        I: (N, P, 3) intensities of the P mask pixels; prior: (P, 3); mask: (H, W) with P pixels.

    Returns:
        (P, 3) unit normals.
    """
    g = np.asarray(I, np.float64).sum(-1)
    n = np.asarray(prior, np.float64)
    U, sv, _ = np.linalg.svd(g.T, full_matrices=False)
    B0 = U[:, :3] * np.sqrt(sv[:3])
    h, w = mask.shape
    Bmap = np.zeros((h, w, 3))
    Bmap[mask] = B0
    A = integrability_gbr(Bmap, mask, smooth=smooth, irls=irls)
    B = B0 @ A.T
    wgt = np.ones(len(n))
    for _ in range(4):
        # residual (I - n n^T) (b + [a b_z, c b_z, (d - 1) b_z]) = 0, linear in (a, c, d)
        Pp = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
        cols = np.zeros((len(n), 3, 3))
        cols[:, 0, 0] = B[:, 2]
        cols[:, 1, 1] = B[:, 2]
        cols[:, 2, 2] = B[:, 2]
        Jm = Pp @ cols  # (P, 3, 3)
        r0 = np.einsum("pij,pj->pi", Pp, B * [1, 1, 0])
        sw = np.sqrt(wgt)[:, None, None]
        theta = np.linalg.lstsq((Jm * sw).reshape(-1, 3), (-(r0 * sw[..., 0])).reshape(-1), rcond=None)[0]
        Bg = np.stack([B[:, 0] + theta[0] * B[:, 2], B[:, 1] + theta[1] * B[:, 2], theta[2] * B[:, 2]], 1)
        if np.sum(wgt * np.sum(Bg * n, 1)) < 0:
            Bg = -Bg
        Bn = Bg / np.maximum(np.linalg.norm(Bg, axis=1, keepdims=True), 1e-12)
        ang = np.degrees(np.arccos(np.clip(np.sum(Bn * n, 1), -1, 1)))
        wgt = 1.0 / (1.0 + (ang / 15.0) ** 2)
    return Bn.astype(np.float32)


def through_gbr(n, G) -> np.ndarray:
    """Unit normals ``G^-T n / |G^-T n|`` (any leading shape; n_z > 0 stays > 0)."""
    b = np.asarray(n, np.float64) @ np.linalg.inv(G)
    return (b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)).astype(np.float32)


def nest_normals(nests) -> np.ndarray:
    """The unit normals of habitats ``(..., 5)`` (as :func:`gpps.kernels.cuckoo.habitat_normal`)."""
    x, y = nests[..., 0], nests[..., 1]
    r2 = x * x + y * y
    n = np.stack([x, y, np.where(r2 < 0.9999, np.sqrt(np.maximum(1.0 - r2, 0.0)), 0.01)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)

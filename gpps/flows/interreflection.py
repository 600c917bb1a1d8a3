"""Reconstruction with the diffuse interreflections taken out of the images (issue 25).

Per-pixel photometric stereo explains each pixel by the lights alone; in a concavity the surface also lights
itself, and the normals bend toward the light the walls send each other.  Our development renders measure the
cost (perf/dev_floor.py: the same Mitsuba scenes with and without interreflections, 12 lights: a Lambertian
ridged surface 2.71 -> 0.23 deg, a sphere on a plane 2.41 -> 0.76).

The compensation (the radiosity equation for Lambertian surfaces, e.g. Nayar, Ikeuchi & Kanade, "Shape from
interreflections", IJCV 6(3), 1991): once a reconstruction gives a surface (depth, normals, albedo ``rho``), the
indirect light in image ``k`` at pixel ``i`` is ``kd_i * S_k(i)`` with ``S_k(i) = sum_j F_ij L_k(j)`` the radiance
gathered from the other patches (:class:`gpps.pipeline.interreflection.Interreflections`) and ``kd = tau * rho``
the physical albedo.  The sources' radiance ``L_k(j)`` is their observed value less the model's specular part
(what a glossy source sends toward the camera is not what it sends elsewhere); the observed images hold every
bounce, so one gather gives all of the indirect light.  The images less ``tau * rho * S`` are reconstructed again.

``tau``, the ratio of the physical albedo to the estimated one, is 1 when the light intensities are radiometric
(the images are ``kd cos`` under unit lights: gpps's renders and our Mitsuba development captures); real captures
may give intensities up to one unknown scale (DiLiGenT's are relative).  The caller may give it (``albedo_scale``):
where it would make the albedo of more than 1 % of the pixels exceed 1 it is lowered to that bound; where the
first reconstruction's albedo is far beyond 1 (:data:`MAX_APPARENT_ALBEDO`) nothing is taken out, with a warning.

**When the scale is unknown** (``albedo_scale=None``, the default), ``tau`` is chosen so that the brightest pixels'
albedo (99th percentile) is ``a`` = :data:`gpps.names.ASSUMED_BRIGHT_ALBEDO` = 1/2.  Why: the gathered radiance
``S`` comes from the images themselves (its scale is theirs), so the light taken out is ``a (rho / rho_99) S``
where the truth is ``rho S``; on a surface of one albedo the light left in (or taken out too much) is
``|rho - a| S``, against ``rho S`` without the compensation.  The compensation gains wherever ``rho > a / 2``, and
over every albedo in [0, 1] the worst case, ``max(a, 1 - a) S``, is smallest at ``a = 1/2``: half that of no
compensation on a white surface, and a black one gets at most what a grey one of albedo 1/2 would have sent
itself.  No figure of any data set chose it.  Measured (perf/results/s39/README.md, our Mitsuba development
captures, 12 lights, ``albedo_scale`` 0.5, 1 (the truth) and 2, two rounds): the 14 concave non-metal captures
all better than without the compensation at half the true scale and at the true scale; at twice it (the rule's
break-even) 9 skipped by the apparent-albedo check, 3 better, and the one run at exactly twice the true scale
worse (rough-plastic spheres, directional, 2.80 -> 3.14 deg).

**Estimating tau from the images does not work** (measured on our development renders, session 20): the least-
squares coefficient of ``rho * S`` in the model's residual came out 0.01 where the truth is 1 (the normals and the
albedo absorb the indirect light: the residual hardly sees it), and its variable projection (only the part no
Lambertian pixel explains) came out between -5.5 and 3.8 (the other misfits of real reflectance dominate that part).

**Where it holds.**  The model is Lambertian: matte surfaces.  On our Mitsuba development captures (12 lights,
``perf/dev_visible_eval.py ... subtract``, perf/results/s20/README.md) a matte ridged surface goes from 2.71 to 0.79
deg (2.02 -> 0.81 under point lights), a sphere on a plane 2.41 -> 2.01, one-pixel steps of rough plastic 8.74 ->
7.33; glossy surfaces gain little or lose (a rough-plastic bowl under point lights 2.42 -> 3.35: its fitted
"albedo" is not a diffuse albedo and its interreflections are glossy).  With the reflectance model chosen by
residual between Blinn-Phong and plastic (``models=("plastic",)``), whose albedo is the diffuse albedo under the
coating, the plastics gain too (bowl 3.17 -> 1.80, bumps 1.67 -> 0.65).

Since session 34 (perf/results/s34/README.md: the receivers' albedo bounded by ``1 / tau``, the later rounds kept on
the first round's model, no round where nothing is sent) no 12-light capture of our development or held-out sets
got worse with it at the true scale.  Since session 39 it is the folder flow's default from
:data:`gpps.names.INTERREFLECTION_MIN_IMAGES` images (:func:`gpps.flows.folder.automatic_interreflections`), one
round, with the assumed scale above, the later reconstruction keeping the first's material and starting every pixel
warm from its normals (``gpps.reconstruct(..., start=...)``: no least squares, DGMC or cold starts); 12-light
development captures (perf/results/s39/README.md): non-diffuse mean 3.83 -> 3.46 deg, matte 2.74 -> 2.08, none
worse.  With three lights it helps matte surfaces and hurts glossy ones (a glossy surface's Blinn-Phong "albedo"
holds some of its lobe), so below that many images it stays off.  Metals are skipped: the first bounce under their
fitted lobe (:meth:`gpps.pipeline.interreflection.Interreflections.gather_model`) predicts their interreflections
from the true surface but not from a reconstruction the interreflections have bent.
"""

from __future__ import annotations

import time

import numpy as np

from gpps._runtime import warp
from gpps.camera import Orthographic
from gpps.names import ASSUMED_BRIGHT_ALBEDO
from gpps.pipeline.interreflection import InterreflectionConfig, Interreflections

__all__ = ["interreflection_terms", "tau_bound", "reconstruct_subtracting", "MAX_APPARENT_ALBEDO", "NEGLIGIBLE_SHARE"]

#: the largest albedo (times ``albedo_scale``, 99th percentile) the compensation accepts from the first
#: reconstruction.  A matte surface's apparent albedo exceeds its true one by the indirect light it receives: a
#: white wall in a deep concavity gathering a third of its light indirectly shows 1.5.  Beyond that the fitted
#: "albedo" is not a diffuse albedo (a glossy or metallic surface, whose lobe the model does not hold) or the light
#: intensities are not radiometric.  (On the development captures the rough conductors show 2.0-2.1, every other
#: capture at most 1.2: any value in 1.25-2 decides the same there.)
MAX_APPARENT_ALBEDO = 1.5

#: below this share of the images' light (summed over the mask) the indirect light is not taken out and no round
#: reconstructs again: a relative change of 1e-6 in the images moves a normal by about 1e-6 rad, and a convex
#: surface (DiLiGenT's ball: 1e-9) sends itself nothing; the rounds would return the first reconstruction
NEGLIGIBLE_SHARE = 1e-6

def _filled_depth(rec) -> np.ndarray:
    """RON's depth on its depth mask, the mask's other pixels filled with the nearest depth (> 0 everywhere)."""
    from scipy import ndimage

    d = np.asarray(rec.depth, np.float64)
    ok = np.asarray(rec.depth_mask, bool) & np.isfinite(d) & (d > 0)
    if not ok.any():
        raise ValueError("depth: the reconstruction has no depth to gather interreflections over")
    idx = ndimage.distance_transform_edt(~ok, return_distances=False, return_indices=True)
    return d[idx[0], idx[1]].astype(np.float32)


def interreflection_terms(images, mask, lights, camera, rec, *, config: InterreflectionConfig | None = None,
                          max_albedo: float = np.inf, glossy: bool = False, device=None) -> dict:
    """The quantities of one compensation round from a reconstruction ``rec`` of ``images``.

    Args:
        images: (N, H, W, 3) the observed images (divided by the light intensities as ``reconstruct`` takes them).
        mask: (H, W) bool; lights, camera: as given to ``reconstruct``.
        rec: its :class:`gpps.flows.reconstruction.Reconstruction` (with a depth).
        config: :class:`InterreflectionConfig`.
        max_albedo: the receivers' albedo is taken as at most this (``1 / tau``: a diffuse surface reflects at
            most what it receives).  A pixel no light reaches (a cast shadow under every light) is fitted with
            any albedo times a vanishing shading, up to 10^5 and more on our development captures; unclipped,
            such a pixel's ``rho * S`` exceeded the whole image's sum.
        glossy: the first bounce under the fitted model at both ends
            (:meth:`gpps.pipeline.interreflection.Interreflections.gather_model`: what a glossy source sends toward
            the receiver and what the receiver's lobe sends on to the camera, each light's cast shadows at the
            sources from the depth) instead of the diffuse gather of the observed radiance; ``B`` is then the
            indirect light itself (per unit ``tau``), not ``rho`` times a gathered radiance, and the sources'
            albedo is clipped at ``max_albedo`` as the receivers' is.

    Returns:
        ``{"B": (N, H, W, 3) rho * S (the indirect light per unit tau, ``rho`` clipped to ``[0, max_albedo]``),
        "sources": S, "stride": stride}``.
    """
    camera = Orthographic() if camera is None else camera
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images: expected (N, H, W, 3) RGB images, got shape {images.shape}")
    n, h, w = images.shape[:3]
    depth = _filled_depth(rec)
    normals = rec.normals
    # (a pixel the solver could not fit may carry a negative or NaN albedo: it reflects nothing here)
    albedo = np.clip(np.nan_to_num(np.asarray(rec.albedo, np.float32)), 0.0, None)
    if glossy:
        from gpps.pipeline.shadows import CastShadows

        kd = np.minimum(albedo, np.float32(max_albedo)) if np.isfinite(max_albedo) else albedo
        with CastShadows((n, h, w), camera, lights, device=device) as cs:
            cs.upload(depth, mask)
            cs.step()
            visible = cs.fetch()
        with Interreflections((n, h, w), camera, config, device=device) as st:
            st.upload(depth, mask, normals, np.zeros((n, h, w), np.float32))  # (no observed radiance used)
            B = st.gather_model(kd, rec.material, lights, visible)
            stride, sources = st.stride, st.sources
        return {"B": B, "sources": sources, "stride": stride}
    with _diffuse_gather(images, mask, lights, camera, rec, config, device, depth=depth) as st:
        S = st.fetch()
        stride, sources = st.stride, st.sources
    kd = np.minimum(albedo, np.float32(max_albedo)) if np.isfinite(max_albedo) else albedo
    S *= kd[None]  # (in place: S is this call's own array)
    return {"B": S, "sources": sources, "stride": stride}


def _diffuse_gather(images, mask, lights, camera, rec, config, device, *, depth=None) -> Interreflections:
    """The stage with the diffuse gather over ``rec``'s surface done (the sources' radiance: ``images`` less the
    model's specular part, at the sources only; ``depth``: :func:`_filled_depth` of ``rec``, when the caller has it);
    the caller closes it (a ``with`` block)."""
    n, h, w = images.shape[:3]
    st = Interreflections((n, h, w), camera, config, device=device)
    try:
        st.upload(_filled_depth(rec) if depth is None else depth, mask, rec.normals, images,
                  less_specular=(rec.material, lights))
        st.step()
    except BaseException:
        st.close()
        raise
    return st


def tau_bound(albedo, mask) -> float:
    """``1 / rho_99``: the largest ``tau`` that keeps the physical albedo of 99 % of the pixels at most 1 (``rho_99``
    the 99th percentile of the albedo's largest channel over the mask, negative and NaN values counted as 0;
    infinite for a black albedo, which reflects nothing whatever ``tau``)."""
    a = np.clip(np.nan_to_num(np.asarray(albedo, np.float64)[np.asarray(mask, bool)]), 0.0, None)
    a = a.max(-1) if a.ndim == 2 else a
    q = float(np.percentile(a, 99)) if a.size else 0.0
    return 1.0 / q if q > 0 else float("inf")


def reconstruct_subtracting(solve, images, mask, lights, camera, *, rounds: int = 1, albedo_scale: float | None = None,
                            config: InterreflectionConfig | None = None, device=None, progress=None):
    """``solve(images)`` (a reconstruction with depth) on the images with the interreflections taken out.

    Args:
        solve: ``solve(images) -> Reconstruction`` (the caller's ``reconstruct`` with its other arguments).  Where
            ``solve`` has a ``frame`` attribute that is not None after its first call (a
            :class:`gpps.flows.reconstruction.ResidentFrame` holding that reconstruction's frame on the device: the
            folder flow's), the later rounds run there: the gathered light is summed and subtracted on the device
            (:meth:`gpps.pipeline.interreflection.Interreflections.subtract_from`) and ``frame.again`` solves the
            frame warm, with the last reconstruction's material; no stack is fetched, checked or uploaded again.
            Otherwise each later round calls ``solve`` with the corrected images.
        images, mask, lights, camera: the capture (as ``solve`` takes them).
        rounds: compensation rounds (each one gather over the last surface and one more ``solve``).
        albedo_scale: ``tau``, the physical albedo over the estimated one (1: radiometric light intensities).
            Where ``tau`` times the albedo exceeds 1 on more than 1 % of the pixels ``tau`` is lowered to
            :func:`tau_bound` (the brightest pixels taken as white; ``info["lowered"]``); where it exceeds
            :data:`MAX_APPARENT_ALBEDO` in the first round nothing is taken out (``info["skipped"]``, a
            :class:`gpps.GppsWarning`).  None (default): the intensities' scale is unknown (relative, as
            DiLiGenT's); ``tau`` is set once, from the first reconstruction, so that the brightest pixels' albedo
            (99th percentile) is :data:`gpps.names.ASSUMED_BRIGHT_ALBEDO` (the module docstring says why).
        config: :class:`InterreflectionConfig`.
        progress: optional ``progress(done, total, message)``, called before each round's gather (``solve``
            reports its own progress in between).

    Returns:
        ``(reconstruction, info)``: the last reconstruction and ``{"tau": [...] per round, "bound": ...,
        "sources": ..., "stride": ..., "indirect_share": [...], "lowered": ..., "skipped": ...}`` (the
        indirect light's share of the images' sum over the mask, per round); ``"negligible": True`` where a
        round's share fell below :data:`NEGLIGIBLE_SHARE` and the rounds stopped without reconstructing again;
        ``"round_seconds"``: ``{"first": s, "gather": [s per round], "solve": [s per round]}`` (wall time);
        ``"scale"``: ``"assumed"`` (``albedo_scale`` None) or ``"given"``, and ``"albedo_scale"`` as given;
        ``"resident"``: whether the later rounds ran on the device-resident frame.
    """
    from gpps._check import warn

    images = np.asarray(images, np.float32)
    m = np.asarray(mask, bool)
    t0 = time.perf_counter()
    rec = solve(images)
    seconds = {"first": time.perf_counter() - t0, "gather": [], "solve": []}
    # (the images' light in the mask: per pixel first, no copy of the masked stack)
    total = max(float(images.sum(axis=(0, 3) if images.ndim == 4 else 0, dtype=np.float64)[m].sum()), 1e-30)
    taus, shares = [], []
    assumed = albedo_scale is None
    info: dict = {"albedo_scale": None if assumed else float(albedo_scale), "scale": "assumed" if assumed else "given",
                  "skipped": False, "lowered": False, "negligible": False}
    tau0 = observed = None
    for r in range(int(rounds)):
        bound = tau_bound(rec.albedo, m)
        if assumed:
            # (once, from the first reconstruction: the capture's scale, which later rounds' albedo must not move;
            # a black albedo reflects nothing whatever tau)
            tau0 = (ASSUMED_BRIGHT_ALBEDO * bound if np.isfinite(bound) else 1.0) if tau0 is None else tau0
        tau = tau0 if assumed else float(albedo_scale)
        if r == 0 and rec.material.brdf == "conductor":
            # (the first bounce under the fitted lobe, interreflection_terms(glossy=True), predicts a metal's
            # interreflections from the true surface (copper ridges: correlation 0.95 with the rendered indirect
            # light) but not from the first reconstruction, whose normals the interreflections bent: there the
            # rounds oscillate and the error does not fall; session 34, perf/results/s34/README.md)
            warn("interreflections: the model chosen is the conductor (a metal: its albedo map weighs a specular "
                 "lobe, there is no diffuse albedo to send light on); the diffuse compensation does not apply and "
                 "the interreflections are left in")
            info.update(skipped=True, bound=None, apparent_albedo=None)
            break
        if r == 0 and not assumed and tau > MAX_APPARENT_ALBEDO * bound:
            warn(f"interreflections: the estimated albedo times albedo_scale ({tau:g}) reaches "
                 f"{tau / bound:.3g} on 1 % of the pixels, beyond what a matte surface lit by itself shows "
                 f"({MAX_APPARENT_ALBEDO:g}): the surface is glossy or metallic (its fitted albedo is no diffuse "
                 "albedo) or the light intensities are not radiometric (give albedo_scale); the interreflections "
                 "are left in")
            info.update(skipped=True, bound=bound, apparent_albedo=tau / bound)
            break
        if tau > bound:  # (the brightest pixels taken as white)
            tau = bound
            info["lowered"] = True
        taus.append(tau)
        if progress is not None:
            progress(r, int(rounds), f"interreflections: gathering over the surface (round {r + 1} of {int(rounds)})")
        t0 = time.perf_counter()
        frame = getattr(solve, "frame", None)
        if frame is not None:
            # (the resident path: the gather's output stays on the device and is taken out of the solver's frame
            # there; one float per receiver comes back for the share)
            camera = Orthographic() if camera is None else camera
            with _diffuse_gather(images, m, lights, camera, rec, config, device) as st:
                shares.append(tau * st.indirect_total(rec.albedo, max_albedo=1.0 / tau) / total)
                info.update(bound=bound if np.isfinite(bound) else None, sources=st.sources, stride=st.stride)
                if shares[-1] >= NEGLIGIBLE_SHARE:
                    if observed is None and int(rounds) > r + 1:  # (later rounds subtract from the observed frame)
                        observed = warp().clone(frame.images)
                    st.subtract_from(frame.images, tau * frame.scale, observed=observed)
            seconds["gather"].append(time.perf_counter() - t0)  # (the sources' radiance, the gather, the frame's update)
            if shares[-1] < NEGLIGIBLE_SHARE:
                info["negligible"] = True
                break
            t0 = time.perf_counter()
            rec = frame.again(rec, progress=progress)
            seconds["solve"].append(time.perf_counter() - t0)
            continue
        terms = interreflection_terms(images, m, lights, camera, rec, config=config, max_albedo=1.0 / tau,
                                      device=device)
        shares.append(tau * float(terms["B"].sum(dtype=np.float64)) / total)  # (B is 0 off the mask)
        seconds["gather"].append(time.perf_counter() - t0)  # (the sources' radiance, the gather, B)
        info.update(bound=bound if np.isfinite(bound) else None, sources=terms["sources"], stride=terms["stride"])
        if shares[-1] < NEGLIGIBLE_SHARE:
            info["negligible"] = True  # (a convex surface sends itself nothing: the images would not change)
            break
        t0 = time.perf_counter()
        corrected = terms.pop("B")  # (this round's own array: images - tau B, clipped at 0, in its place)
        np.multiply(corrected, np.float32(-tau), out=corrected)
        corrected += images
        rec = solve(np.maximum(corrected, 0.0, out=corrected))
        seconds["solve"].append(time.perf_counter() - t0)  # (the images' update and the reconstruction)
    info.update(tau=taus, indirect_share=shares, round_seconds=seconds, resident=getattr(solve, "frame", None) is not None)
    return rec, info

"""Diffuse interreflections over a depth map: the form factors between surface patches seen at two pixels.

Device math only; the buffers live in :class:`gpps.pipeline.interreflection.Interreflections`.

Every mask pixel is a small surface patch: the point ``P`` seen at the pixel (its depth, :func:`pixel_point`),
the normal ``n`` and the area ``A`` of the surface the pixel sees.  For a receiver ``r`` and a source ``s`` with
``w = P_s - P_r``, ``d = |w|`` and ``omega = w / d`` the form factor of the source's patch seen from the receiver
is (the radiosity kernel, e.g. Cohen & Wallace, "Radiosity and realistic image synthesis", eq. 4.14)::

    F_rs = V_rs * max(0, n_r . omega) * max(0, -n_s . omega) * A_s / (pi d^2)

with ``V_rs`` the visibility of the source from the receiver: 1 unless the depth map lies in front of the segment
between them (the march of :func:`gpps.kernels.shadows.march`, the cast-shadow rule with the segment in place of
the ray toward a light, ending a tolerance short of the source so that the source's own surface does not hide it).
A Lambertian receiver of albedo ``kd_r`` under the radiance ``L_s`` leaving the sources then reflects, toward the
camera, the radiance ``kd_r * sum_s F_rs L_s`` (one gather; the observed images already hold every bounce, so one
gather of the observed radiance gives all the indirect light, not only its first bounce).

The patch area: a pixel of the pinhole camera spans the solid angle ``cos^3(alpha) / (fx fy)`` (``alpha`` the
ray's angle off the optical axis); at the distance ``|P|`` and with the surface tilted by ``theta`` from the
view direction the patch has the area ``|P|^2 cos^3(alpha) / (fx fy cos theta)``; under the orthographic camera
``pixel_size^2 / cos theta``.  ``cos theta`` is clamped at :data:`MIN_COS_VIEW` (a grazing patch would have an
unbounded area; the clamp caps its weight, the pixel's radiance being as doubtful as its normal there).

Sources are a subset of the mask pixels (every ``stride``-th row and column), each standing for ``stride^2``
pixels: the caller passes ``area_scale = stride^2``.  Sources closer than :data:`MIN_SEPARATION_PX` pixels to the
receiver are left out: their patches are nearly coplanar with it (``F`` ~ 0) and the point-to-point kernel is
singular there.
"""

import warp as wp

from gpps.kernels.brdf import (CameraParams, LightParams, MaterialParams, brdf_terms, light_dir, light_radiance,
                               pixel_point, shade, view_dir)
from gpps.kernels.shadows import march

__all__ = ["form_factor_kernel", "gather_kernel", "model_gather_kernel", "source_specular_kernel", "MIN_COS_VIEW",
           "MIN_SEPARATION_PX"]

MIN_COS_VIEW = wp.constant(0.1)
MIN_SEPARATION_PX = wp.constant(1.5)
PI = wp.constant(3.14159265358979)


@wp.func
def patch_area(cam: CameraParams, p: wp.vec3, n: wp.vec3):
    """Area (scene units^2) of the surface patch seen at one pixel: the point ``p`` with the unit normal ``n``."""
    v = view_dir(cam, p)
    c = wp.max(wp.dot(n, v), MIN_COS_VIEW)
    if cam.perspective != 0:
        dist = wp.length(p)
        cos_a = -p[2] / wp.max(dist, 1.0e-30)
        return dist * dist * cos_a * cos_a * cos_a / (cam.fx * cam.fy * c)
    return cam.pixel_size * cam.pixel_size / c


@wp.kernel(enable_backward=False)
def form_factor_kernel(
    depth: wp.array2d(dtype=wp.float32),
    mask: wp.array2d(dtype=wp.uint8),
    normals: wp.array2d(dtype=wp.vec3),
    cam: CameraParams,
    recv: wp.array(dtype=wp.vec2i),
    src: wp.array(dtype=wp.vec2i),
    area_scale: float,
    dmin: wp.array(dtype=wp.float32),
    tau: float,
    step_px: float,
    max_steps: int,
    visibility: int,
    F: wp.array2d(dtype=wp.float32),
):
    """``F[r, s]`` of the module docstring for every receiver ``r`` and source ``s`` (dim (R, S)).

    Args:
        depth: (H, W) depth (> 0 in the mask, scene units); mask: (H, W) 1 on the object.
        normals: (H, W) unit normals (gpps frame).
        cam: the camera.
        recv: (R,) receiver pixels (row, column); src: (S,) source pixels (row, column), all in the mask.
        area_scale: pixels each source stands for (``stride^2``).
        dmin: (1,) the smallest depth in the mask (:data:`gpps.kernels.shadows.min_depth_kernel`).
        tau: the march's tolerance in pixel widths; step_px: its step in pixels; max_steps: its most steps.
        visibility: 1: march for ``V``; 0: ``V = 1`` (no occlusion test).
        F: (R, S) out, 1 / steradian-free: the fraction of the source's radiance the receiver gathers.
    """
    r, s = wp.tid()
    ri = recv[r]
    si = src[s]
    du = float(ri[1] - si[1])
    dv = float(ri[0] - si[0])
    if du * du + dv * dv < MIN_SEPARATION_PX * MIN_SEPARATION_PX:
        F[r, s] = 0.0
        return
    pr = pixel_point(cam, ri[0], ri[1], depth[ri[0], ri[1]])
    ps = pixel_point(cam, si[0], si[1], depth[si[0], si[1]])
    nr = normals[ri[0], ri[1]]
    ns = normals[si[0], si[1]]
    w = ps - pr
    d = wp.length(w)
    if d <= 0.0:
        F[r, s] = 0.0
        return
    om = w / d
    cr = wp.dot(nr, om)
    cs = -wp.dot(ns, om)
    if cr <= 0.0 or cs <= 0.0:
        F[r, s] = 0.0
        return
    f = cr * cs * area_scale * patch_area(cam, ps, ns) / (PI * d * d)
    if visibility != 0:
        # the segment, ending tau footprints short of the source (its own surface must not hide it)
        fp = wp.max(-ps[2], 1.0e-30) / wp.max(cam.fx, cam.fy)
        if cam.perspective == 0:
            fp = cam.pixel_size
        t_end = d - tau * fp
        if t_end > 0.0:
            if march(depth, mask, cam, pr, om, t_end, dmin[0], tau, step_px, max_steps) == 0:
                f = 0.0
    F[r, s] = f


@wp.kernel(enable_backward=False)
def gather_kernel(F: wp.array2d(dtype=wp.float32), x: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.float32)):
    """``out[r, c] = sum_s F[r, s] x[s, c]`` (dim (R, C)): the gathered radiance of every receiver and column
    (a column = one image's colour channel)."""
    r, c = wp.tid()
    acc = float(0.0)
    for s in range(F.shape[1]):
        acc += F[r, s] * x[s, c]
    out[r, c] = acc


@wp.kernel(enable_backward=False)
def model_gather_kernel(
    F: wp.array2d(dtype=wp.float32),
    depth: wp.array2d(dtype=wp.float32),
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
    visible: wp.array3d(dtype=wp.uint8),
    mat: MaterialParams,
    lights: LightParams,
    cam: CameraParams,
    recv: wp.array(dtype=wp.vec2i),
    src: wp.array(dtype=wp.vec2i),
    out: wp.array2d(dtype=wp.vec3),
):
    """One bounce of glossy (or any modelled) interreflection: the radiance each receiver sends toward the camera
    from the direct light its sources send it, both ends under the reflectance model (dim (R, N)).

    For receiver ``r`` under light ``k``, with ``omega`` the unit direction from ``r`` to source ``s``::

        out[r, k] = sum_s (F_rs / (n_r . omega)) * T_r(omega -> camera) * L_k,s(-> r)

    ``T_r(l -> v) = albedo_r * t0 + ks * t1`` is the model's reflected radiance per unit radiance arriving from
    ``l`` (:func:`gpps.kernels.brdf.brdf_terms`: its cosine included, so ``F`` is divided by the receiver's
    cosine; for a Lambertian receiver this is ``albedo_r * F_rs``, :func:`gather_kernel`'s term), and
    ``L_k,s(-> r)`` the source's direct radiance toward the receiver under light ``k``
    (:func:`gpps.kernels.brdf.shade` with the view direction ``-omega``), zero where light ``k`` is cast-shadowed
    at the source (``visible``).  A glossy source sends toward the receiver what it does not send toward the
    camera, so the observed images cannot stand for it (they do in :func:`gather_kernel`, for diffuse sources);
    the model fitted to the images can.  Only the first bounce: the light the sources receive indirectly is not
    sent on (its share is the albedo times this one's).

    Args:
        F: (R, S) form factors of :func:`form_factor_kernel` for these receivers (visibility included).
        depth, normals, albedo: (H, W) the surface (depth > 0 in the mask, unit normals, RGB albedo).
        visible: (N, H, W) 1 where light ``k`` reaches the pixel (:mod:`gpps.pipeline.shadows`).
        mat: the reflectance model; lights: the N lights; cam: the camera.
        recv: (R,) receiver pixels; src: (S,) source pixels (row, column).
        out: (R, N) RGB radiance toward the camera, per receiver and light.
    """
    r, k = wp.tid()
    ri = recv[r]
    pr = pixel_point(cam, ri[0], ri[1], depth[ri[0], ri[1]])
    nr = normals[ri[0], ri[1]]
    ar = albedo[ri[0], ri[1]]
    vr = view_dir(cam, pr)
    acc = wp.vec3(0.0, 0.0, 0.0)
    for s in range(F.shape[1]):
        f = F[r, s]
        if f > 0.0:
            si = src[s]
            if visible[k, si[0], si[1]] != wp.uint8(0):
                ps = pixel_point(cam, si[0], si[1], depth[si[0], si[1]])
                om = wp.normalize(ps - pr)
                cr = wp.dot(nr, om)
                if cr > 0.0:
                    ls = light_dir(lights, k, ps)
                    Ls = shade(mat, albedo[si[0], si[1]], normals[si[0], si[1]], ls, -om,
                               light_radiance(lights, k, ps))
                    t = brdf_terms(mat, nr, om, vr)
                    acc = acc + (f / cr) * wp.cw_mul(ar * t[0] + wp.vec3(mat.ks * t[1]), Ls)
    out[r, k] = acc


@wp.kernel(enable_backward=False)
def source_specular_kernel(
    depth: wp.array2d(dtype=wp.float32),
    normals: wp.array2d(dtype=wp.vec3),
    mat: MaterialParams,
    lights: LightParams,
    cam: CameraParams,
    src: wp.array(dtype=wp.vec2i),
    out: wp.array2d(dtype=wp.vec3),
):
    """The model's specular part toward the camera at each source pixel under each light, ``E_k * ks * s`` (dim
    (S, N)): what a rendered image less its render with ``ks = 0`` holds there (:func:`gpps.kernels.brdf.shade`;
    the albedo-weighted term is the same in both and cancels), computed at the sources only.

    Args:
        depth, normals: (H, W) the surface; mat: the model; lights: the N lights; cam: the camera.
        src: (S,) source pixels (row, column).
        out: (S, N) RGB specular radiance.
    """
    s, k = wp.tid()
    si = src[s]
    p = pixel_point(cam, si[0], si[1], depth[si[0], si[1]])
    t = brdf_terms(mat, normals[si[0], si[1]], light_dir(lights, k, p), view_dir(cam, p))
    out[s, k] = wp.cw_mul(light_radiance(lights, k, p), wp.vec3(mat.ks * t[1]))

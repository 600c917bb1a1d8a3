"""Device math of the uncalibrated refinement (seed 5.1-5.7): a differentiable image loss.

The loss is differentiated by Warp's autodiff (``wp.Tape``) with respect to the
normals, albedo, lights and the shared specular parameters.
"""

import warp as wp

from gpps.kernels.brdf import ashikhmin_shirley_spec, blinn_phong_spec


@wp.kernel
def lambert_as_loss(
    images: wp.array2d(dtype=wp.vec3),
    weights: wp.array2d(dtype=wp.float32),
    views: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    albedo: wp.array(dtype=wp.vec3),
    lights: wp.array(dtype=wp.vec3),
    spec: wp.array(dtype=wp.float32),
    f0: float,
    lobe: int,
    robust: float,
    loss: wp.array(dtype=wp.float32),
):
    """Weighted squared error of the Lambertian + Ashikhmin-Shirley image model.

    One thread per (image k, pixel p).  The model for light ``s_k`` (direction
    ``s/|s|``, intensity ``|s|``), free normal ``n_p`` (normalised here) and RGB
    albedo ``a_p``::

        I = |s| (a max(n.l, 0) + ks * AS(n, l, v; eta, eta, f0))

    with ``ks = exp(spec[0])`` and ``eta = exp(spec[1])`` (log-parameters keep
    them positive); ``lobe`` 0: no specular term, 1: Ashikhmin-Shirley (5.1-5.2,
    isotropic), 2: Blinn-Phong (2.21) with exponent eta.  The loss adds ``w_kp |I - I_kp|^2``,
    or with ``robust = c > 0`` the Cauchy loss ``w_kp c^2 log(1 + |I - I_kp|^2 / c^2)`` (cast
    shadows, inter-reflections and other observations no model term explains then pull less).

    Args:
        images: (N, P) observed RGB.
        weights: (N, P) per-observation weights (0 drops shadows / saturation).
        views: (P,) unit view vectors.
        normals, albedo: (P,) parameters.
        lights: (N,) parameters.
        spec: (2,) log ks, log eta.
        robust: Cauchy scale (intensity units); 0 for least squares.
        loss: (1,) accumulator (zero it first).
    """
    k, p = wp.tid()
    w = weights[k, p]
    if w == 0.0:
        return
    n = wp.normalize(normals[p])
    s = lights[k]
    e = wp.length(s)
    l = s / e
    nl = wp.dot(n, l)
    pred = wp.vec3(0.0)
    if nl > 0.0:
        pred = albedo[p] * nl
        if lobe != 0:
            ks = wp.exp(spec[0])
            eta = wp.exp(spec[1])
            sp = float(0.0)
            if lobe == 1:
                sp = ashikhmin_shirley_spec(n, l, views[p], eta, eta, f0)
            else:
                sp = blinn_phong_spec(n, l, views[p], eta)
            pred = pred + wp.vec3(ks * sp)
        pred = pred * e
    r = pred - images[k, p]
    r2 = wp.dot(r, r)
    if robust > 0.0:
        c2 = robust * robust
        r2 = c2 * wp.log(1.0 + r2 / c2)
    wp.atomic_add(loss, 0, w * r2)

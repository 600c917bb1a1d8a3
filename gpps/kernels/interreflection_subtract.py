"""The gathered indirect light applied to a frame on the device: its sum, and the frame less it.

Device math only; the buffers live in :class:`gpps.pipeline.interreflection.Interreflections` (its gather ``S``, (R,
3N) float32, receiver ``r`` at row and column ``recv[r]``, column ``3 k + c`` image ``k``'s channel ``c``) and in the
pixel solver (the frame, (N, H, W) ``vec3``).  A Lambertian receiver of albedo ``kd`` shows the indirect light
``kd * S`` (:mod:`gpps.kernels.interreflection`); the compensation (:mod:`gpps.flows.interreflection`) takes
``coef * kd * S`` out of the images, clipped at 0, with ``kd`` the fitted albedo clipped to ``[0, max_albedo]`` (a NaN
albedo counts as 0) and ``coef`` the albedo's scale ``tau`` times the frame's working scale.  Apart from the clip
these are the host's ``np.clip(nan_to_num(albedo), 0, max_albedo) * S`` and ``max(images - coef * that, 0)``.

A kernel of its own file: the gather's module (and its compiled code) stays as it was.
"""

import warp as wp

__all__ = ["receiver_albedo", "indirect_sums_kernel", "subtract_indirect_kernel"]


@wp.func
def receiver_albedo(albedo: wp.array2d(dtype=wp.vec3), i: int, j: int, max_albedo: float):
    """The receiver's albedo clipped to ``[0, max_albedo]`` per channel (NaN: 0)."""
    a = albedo[i, j]
    out = wp.vec3(0.0, 0.0, 0.0)
    for c in range(3):
        v = a[c]
        if v > 0.0:  # (False for NaN)
            out[c] = wp.min(v, max_albedo)
    return out


@wp.kernel(enable_backward=False)
def indirect_sums_kernel(
    S: wp.array2d(dtype=wp.float32),
    recv: wp.array(dtype=wp.vec2i),
    albedo: wp.array2d(dtype=wp.vec3),
    max_albedo: float,
    sums: wp.array(dtype=wp.float32),
):
    """``sums[r] = sum_k sum_c kd[c] S[r, 3 k + c]`` (dim R): each receiver's indirect light over every image and
    channel, per unit ``tau``."""
    r = wp.tid()
    p = recv[r]
    a = receiver_albedo(albedo, p[0], p[1], max_albedo)
    acc = float(0.0)
    for k in range(S.shape[1] // 3):
        acc += a[0] * S[r, 3 * k] + a[1] * S[r, 3 * k + 1] + a[2] * S[r, 3 * k + 2]
    sums[r] = acc


@wp.kernel(enable_backward=False)
def subtract_indirect_kernel(
    observed: wp.array3d(dtype=wp.vec3),
    S: wp.array2d(dtype=wp.float32),
    recv: wp.array(dtype=wp.vec2i),
    albedo: wp.array2d(dtype=wp.vec3),
    max_albedo: float,
    coef: float,
    frame: wp.array3d(dtype=wp.vec3),
):
    """``frame[k, i, j] = max(observed[k, i, j] - coef * kd * S[r, 3k:3k+3], 0)`` per channel (dim (R, N), ``(i, j)
    = recv[r]``); ``observed`` may be ``frame`` itself (each element read, then written, by one thread)."""
    r, k = wp.tid()
    p = recv[r]
    a = receiver_albedo(albedo, p[0], p[1], max_albedo)
    o = observed[k, p[0], p[1]]
    s = wp.vec3(S[r, 3 * k], S[r, 3 * k + 1], S[r, 3 * k + 2])
    frame[k, p[0], p[1]] = wp.vec3(wp.max(o[0] - coef * (a[0] * s[0]), 0.0), wp.max(o[1] - coef * (a[1] * s[1]), 0.0),
                                   wp.max(o[2] - coef * (a[2] * s[2]), 0.0))

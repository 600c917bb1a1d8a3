"""Device reductions of a RON round (seed 4.1.10, Algorithm 2): its energy and its normal change.

Device math only; the buffers live in :class:`gpps.pipeline.ron_rounds.DeviceRounds`.  One thread a run of
:data:`ROUND_CHUNK` pixels of a row (launch dim ``(H, ceil(W / ROUND_CHUNK))``) sums its mask pixels in float64
and adds its totals atomically.  (One thread a whole row ran 256 float64 ``atan2`` in sequence per thread on
only H threads: 0.24 ms a round on an H100 at 256^2.)

* ``sums[0]``: the squared residuals (the round's energy is their mean, RON's ``_energy``);
* ``sums[1]``: the angles (radians) between each pixel's normal and its previous one,
  ``atan2(|a x b|, a . b)`` in float64 (exact for unit and non-unit vectors alike; 90 degrees where
  either vector is zero), RON's ``normal_change_deg`` the mean in degrees;
* ``sums[2]``: the mask pixels.
"""

import warp as wp

__all__ = ["round_sums_kernel", "ROUND_CHUNK"]

ROUND_CHUNK = wp.constant(16)  # pixels of a row per thread


@wp.kernel(enable_backward=False)
def round_sums_kernel(
    mask: wp.array2d(dtype=wp.uint8),
    residual: wp.array2d(dtype=wp.float32),
    normals: wp.array2d(dtype=wp.vec3),
    prev: wp.array2d(dtype=wp.vec3),
    sums: wp.array(dtype=wp.float64),
):
    i, c = wp.tid()
    j0 = c * ROUND_CHUNK
    j1 = wp.min(j0 + ROUND_CHUNK, mask.shape[1])
    se = wp.float64(0.0)
    sa = wp.float64(0.0)
    cnt = wp.float64(0.0)
    half_pi = wp.float64(1.5707963267948966)
    for j in range(j0, j1):
        if mask[i, j] != wp.uint8(0):
            r = wp.float64(residual[i, j])
            se += r * r
            a = normals[i, j]
            b = prev[i, j]
            a64 = wp.vec3d(wp.float64(a[0]), wp.float64(a[1]), wp.float64(a[2]))
            b64 = wp.vec3d(wp.float64(b[0]), wp.float64(b[1]), wp.float64(b[2]))
            if wp.dot(a64, a64) > wp.float64(0.0) and wp.dot(b64, b64) > wp.float64(0.0):
                sa += wp.atan2(wp.length(wp.cross(a64, b64)), wp.dot(a64, b64))
            else:
                sa += half_pi
            cnt += wp.float64(1.0)
    wp.atomic_add(sums, 0, se)
    wp.atomic_add(sums, 1, sa)
    wp.atomic_add(sums, 2, cnt)

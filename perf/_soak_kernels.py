"""Device math of perf/stream_soak.py: the largest angle between two normal maps (kernels live in real files)."""

import warp as wp


@wp.kernel(enable_backward=False)
def max_angle(a: wp.array2d(dtype=wp.vec3), b: wp.array2d(dtype=wp.vec3), mask: wp.array2d(dtype=wp.uint8),
              out: wp.array(dtype=wp.float32)):
    """out[0] = max over the mask of the angle (degrees) between a and b (atomic max; zero out[0] first)."""
    i, j = wp.tid()
    if mask[i, j] == 0:
        return
    c = wp.clamp(wp.dot(wp.normalize(a[i, j]), wp.normalize(b[i, j])), -1.0, 1.0)
    s = wp.length(wp.cross(wp.normalize(a[i, j]), wp.normalize(b[i, j])))
    wp.atomic_max(out, 0, wp.degrees(wp.atan2(s, c)))

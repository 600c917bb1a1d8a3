"""Frame conversion for streams: raw camera frames (uint8 / uint16 / float32) to the solver's images.

Device math only; :mod:`gpps.pipeline.stream` owns the buffers and launches.
"""

import warp as wp


def _make_convert(dtype, tag: str):
    @wp.kernel(name="convert_" + tag, enable_backward=False)
    def convert(raw: wp.array4d(dtype=dtype), gain: wp.array2d(dtype=wp.float32), images: wp.array3d(dtype=wp.vec3)):
        """images[k, i, j, c] = raw[k, i, j, c or 0] * gain[k, c].

        Args:
            raw: (N, H, W, C) frames, C = 1 (grey, copied to the 3 channels) or 3 (RGB).
            gain: (N, 3) per light and channel: 1 / (full scale * light intensity).
            images: (N, H, W) RGB observations (output).
        """
        k, i, j = wp.tid()
        g = gain[k]
        if raw.shape[3] == 1:
            v = float(raw[k, i, j, 0])
            images[k, i, j] = wp.vec3(v * g[0], v * g[1], v * g[2])
        else:
            images[k, i, j] = wp.vec3(float(raw[k, i, j, 0]) * g[0], float(raw[k, i, j, 1]) * g[1], float(raw[k, i, j, 2]) * g[2])

    return convert


convert_uint8 = _make_convert(wp.uint8, "uint8")
convert_uint16 = _make_convert(wp.uint16, "uint16")
convert_float32 = _make_convert(wp.float32, "float32")


@wp.kernel(enable_backward=False)
def count_nonfinite(raw: wp.array4d(dtype=wp.float32), count: wp.array(dtype=wp.int32)):
    """count[0] += number of NaN / inf values in raw."""
    k, i, j = wp.tid()
    for c in range(raw.shape[3]):
        v = raw[k, i, j, c]
        if not wp.isfinite(v):
            wp.atomic_add(count, 0, 1)

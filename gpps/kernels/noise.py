"""Immerkaer's noise estimate of a frame on the device (device math only).

:func:`gpps.pipeline.solver.estimate_noise` on the host reads, for each image, the pixels of
:func:`gpps.host.observations.noise_selection` whose 3x3 neighbourhood is lit (grey value > 0), applies the kernel
``K = [[1, -2, 1], [-2, 4, -2], [1, -2, 1]]`` to the grey values (the channels' float32 mean, summed left to right)
and takes the median of the magnitudes over ``0.6745 * 6``.  Here :func:`noise_values_kernel` writes each selected
pixel's ``|I * K|`` (the nine terms summed in the host's order; the taps' factors are powers of two, so a fused
multiply-add rounds as the host's multiply then add) or ``+inf`` for a pixel left out, one row of ``keys`` an image,
and counts the values; after a sort of each row (:func:`warp.utils.radix_sort_pairs`), :func:`noise_median_kernel`
takes numpy's median (the middle value, or the float32 mean of the middle two).  The same bits as the host
(tests/test_noise_device.py).
"""

import warp as wp

#: the fewest values an image's estimate needs (fewer: 0, unknown), as the host's
MIN_VALUES = wp.constant(64)


@wp.func
def _grey(c: wp.vec3):
    """The channels' float32 mean as the host takes it: ``(r + g) + b``, then divided by 3."""
    return ((c[0] + c[1]) + c[2]) / wp.float32(3.0)


@wp.kernel(enable_backward=False)
def noise_values_kernel(images: wp.array3d(dtype=wp.vec3), rows: wp.array(dtype=wp.int32),
                        sel: wp.array2d(dtype=wp.uint8), c0: int, keys: wp.array2d(dtype=wp.float32),
                        counts: wp.array(dtype=wp.int32)):
    """One selected pixel of one image: ``keys[k, r * C + c]`` = its ``|I * K|``, or ``+inf`` when it is not in
    the selection or a tap is dark; ``counts[k]`` += 1 for a value.

    Args:
        images: (N, H, W) RGB observations.
        rows: (R,) the selection's rows (neighbourhood rows ``r .. r + 2``).
        sel: (R, C) 1 where the pixel's neighbourhood lies in the mask (centre column ``c0 + 1 + c``).
        c0: the selection's first image column.
        keys: (N, >= 2 R C) the values (written in the first R C slots of each row).
        counts: (N,) the values of each image (zeroed before the launch).
    """
    k, r, c = wp.tid()
    ncol = sel.shape[1]
    slot = r * ncol + c
    keys[k, slot] = wp.float32(wp.inf)
    if sel[r, c] == wp.uint8(0):
        return
    i0 = rows[r]
    j0 = c0 + c
    g00 = _grey(images[k, i0, j0])
    g01 = _grey(images[k, i0, j0 + 1])
    g02 = _grey(images[k, i0, j0 + 2])
    g10 = _grey(images[k, i0 + 1, j0])
    g11 = _grey(images[k, i0 + 1, j0 + 1])
    g12 = _grey(images[k, i0 + 1, j0 + 2])
    g20 = _grey(images[k, i0 + 2, j0])
    g21 = _grey(images[k, i0 + 2, j0 + 1])
    g22 = _grey(images[k, i0 + 2, j0 + 2])
    zero = wp.float32(0.0)
    if not (g00 > zero and g01 > zero and g02 > zero and g10 > zero and g11 > zero and g12 > zero
            and g20 > zero and g21 > zero and g22 > zero):
        return
    two = wp.float32(-2.0)
    lap = g00
    lap = lap + g01 * two
    lap = lap + g02
    lap = lap + g10 * two
    lap = lap + g11 * wp.float32(4.0)
    lap = lap + g12 * two
    lap = lap + g20
    lap = lap + g21 * two
    lap = lap + g22
    keys[k, slot] = wp.abs(lap)
    wp.atomic_add(counts, k, 1)


@wp.kernel(enable_backward=False)
def noise_median_kernel(keys: wp.array2d(dtype=wp.float32), counts: wp.array(dtype=wp.int32),
                        out: wp.array(dtype=wp.float32)):
    """``out[k]`` = the median of image ``k``'s sorted values over ``0.6745 * 6`` (float64, then float32), or 0 with
    fewer than :data:`MIN_VALUES` values."""
    k = wp.tid()
    n = counts[k]
    if n < MIN_VALUES:
        out[k] = wp.float32(0.0)
        return
    j = (n - 1) // 2
    med = keys[k, j]
    if n % 2 == 0:
        med = (keys[k, j] + keys[k, j + 1]) / wp.float32(2.0)
    out[k] = wp.float32(wp.float64(med) / (wp.float64(0.6745) * wp.float64(6.0)))

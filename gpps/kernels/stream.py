"""Frame conversion for streams: raw camera frames (uint8 / uint16 / float32) to the solver's images.

Device math only; :mod:`gpps.pipeline.stream` owns the buffers and launches.
"""

import warp as wp

from gpps import names

FLAG_FEW_OBSERVATIONS = wp.constant(names.FLAG_FEW_OBSERVATIONS)


def _make_convert(dtype, tag: str):
    @wp.kernel(name="convert_" + tag, enable_backward=False)
    def convert(raw: wp.array4d(dtype=dtype), gain: wp.array2d(dtype=wp.float32), saturation: float,
                images: wp.array3d(dtype=wp.vec3), valid: wp.array3d(dtype=wp.uint8)):
        """images[k, i, j, c] = raw[k, i, j, c or 0] * gain[k, c]; valid[k, i, j] = 0 where a raw channel is at or
        above ``saturation`` (a clipped observation, dropped from the fit), else 1.

        Args:
            raw: (N, H, W, C) frames, C = 1 (grey, copied to the 3 channels) or 3 (RGB).
            gain: (N, 3) per light and channel: 1 / (full scale * light intensity).
            saturation: the raw level of a clipped channel (raw units); <= 0: every observation is valid.
            images: (N, H, W) RGB observations (output).
            valid: (N, H, W) the observations to use (output).
        """
        k, i, j = wp.tid()
        g = gain[k]
        top = float(0.0)
        if raw.shape[3] == 1:
            v = float(raw[k, i, j, 0])
            images[k, i, j] = wp.vec3(v * g[0], v * g[1], v * g[2])
            top = v
        else:
            r = float(raw[k, i, j, 0])
            gr = float(raw[k, i, j, 1])
            b = float(raw[k, i, j, 2])
            images[k, i, j] = wp.vec3(r * g[0], gr * g[1], b * g[2])
            top = wp.max(r, wp.max(gr, b))
        ok = wp.uint8(1)
        if saturation > 0.0 and top >= saturation:
            ok = wp.uint8(0)
        valid[k, i, j] = ok

    return convert


convert_uint8 = _make_convert(wp.uint8, "uint8")
convert_uint16 = _make_convert(wp.uint16, "uint16")
convert_float32 = _make_convert(wp.float32, "float32")


@wp.kernel(enable_backward=False)
def count_invalid(raw: wp.array4d(dtype=wp.float32), count: wp.array(dtype=wp.int32)):
    """count[0] += number of NaN / inf values in raw, count[1] += number of negative values."""
    k, i, j = wp.tid()
    for c in range(raw.shape[3]):
        v = raw[k, i, j, c]
        if not wp.isfinite(v):
            wp.atomic_add(count, 0, 1)
        elif v < 0.0:
            wp.atomic_add(count, 1, 1)


# slots of the per-frame statistics (float32 sums, zeroed before each frame)
STAT_LIT = 0  # observations (light, pixel in the mask) whose grey value is lit
STAT_SATURATED = 1  # observations with a channel at or above the saturation level
STAT_GREY = 2  # sum of grey values (solver units) over the mask
STAT_HF = 3  # sum of |Immerkaer Laplacian| of the grey values over interior mask pixels
STAT_HF_GREY = 4  # sum of grey values over the same interior pixels
STAT_RESIDUAL = 5  # sum of the per-pixel residual after the solve
STAT_REDONE = 6  # pixels re-solved cold
STAT_DETERMINED = 7  # mask pixels whose solve had 3 or more valid observations (the residual's pixels)
N_STATS = 8
# the sums are spread over this many slots (rows of the (STAT_SLOTS, N_STATS) array, picked by pixel) so that
# a frame's atomics do not all hit one address: the host adds the slots up after its one read-back
STAT_SLOTS = 256


@wp.func
def _grey(v: wp.vec3) -> float:
    return (v[0] + v[1] + v[2]) / 3.0


STAT_CHUNK = 8  # pixels of a row per thread of frame_stats and residual_sum (local sums: one atomic per statistic
# and thread): neighbouring pixels in frame_stats, ceil(W / STAT_CHUNK) columns apart in residual_sum

# a misfit (refresh_rows) is retried again only when its residual exceeds this factor times the residual it kept
# after its last cold re-solve.  The residual is an RMS: under noise alone its square is a chi-square of 4 degrees
# of freedom (3 x 3 observations, 5 unknowns) times a constant, which exceeds 4 x its mean with probability 0.3 %,
# so a pixel whose multi-start solve found nothing better is not solved again for the noise of the next frames,
# while one that a warm start leaves in a wrong basin rises further.  (On a static scene the retries re-solved the
# same ~70 misfits of 1M pixels every period for nothing: 0.74 ms of a 2.19 ms known-material frame on an H200,
# perf/stream_frame_split.py, perf/results/s26/README.md.)
RETRY_FLOOR_FACTOR = 2.0
HF_STEP_I = 2  # the noise statistic's sub-grid: every 2nd row ...
HF_STEP_J = 4  # ... and every 4th column (1/8 of the pixels)


@wp.kernel(enable_backward=False)
def frame_stats(images: wp.array3d(dtype=wp.vec3), mask: wp.array2d(dtype=wp.uint8),
                intensity: wp.array2d(dtype=wp.float32), lit_level: float, saturation: float,
                stats: wp.array2d(dtype=wp.float32)):
    """Cheap sanity statistics of one converted frame; one thread per ``STAT_CHUNK`` pixels of a row, all lights.

    An observation is lit when its grey value exceeds ``lit_level`` of full
    scale, saturated when a channel reaches ``saturation`` of full scale
    (both as fractions of full scale: ``images * intensity``).

    The high-frequency ratio ``STAT_HF / (6 STAT_HF_GREY)`` is the Immerkaer
    noise estimate (see :func:`gpps.pipeline.solver.estimate_noise`) of the
    *shading ratios* ``r_k = N I_k / sum_l I_l`` relative to their level,
    weighted by the pixel's brightness: the albedo (any texture, down to single
    pixels) cancels in the ratio, which is a smooth function of the normal on a
    lit surface, while noise does not cancel.  Measured on gpps renders
    (sphere, bumps, microprint; smooth, textured and pixel-checkerboard
    albedo; 8 and 16 bit): 0.0001-0.008; uniform noise frames: 0.22 (RGB) and
    0.43 (grey).  Pixels whose 3x3
    neighbourhood leaves the mask or is dark (mean grey below ``lit_level`` of
    full scale, in solver units) are left out, and it is taken on the sub-grid
    of every ``HF_STEP_I``-th row and ``HF_STEP_J``-th column.  Each thread sums its ``STAT_CHUNK``
    neighbouring pixels locally and adds each statistic once (atomics spread over ``STAT_SLOTS`` rows).
    (Every thread of a warp meets its stencils at the same steps of its loop: with a thread's pixels
    interleaved across the row instead, so that the warp's loads coalesce, the threads met them at different
    steps and the kernel took 0.51 ms at 1024^2 on an H200 against 0.11.)

    Args:
        images: (N, H, W) converted observations (solver units).
        mask: (H, W) 1 inside the mask.
        intensity: (N, 3) the light intensities the conversion divided by.
        lit_level, saturation: fractions of full scale.
        stats: (STAT_SLOTS, N_STATS) partial sums.
    """
    i, jc = wp.tid()
    h = images.shape[1]
    w = images.shape[2]
    nl = images.shape[0]
    ncol = (w + STAT_CHUNK - 1) // STAT_CHUNK
    n_lit = float(0.0)
    n_sat = float(0.0)
    grey = float(0.0)
    hf = float(0.0)
    hf_grey = float(0.0)
    for jj in range(STAT_CHUNK):
        j = jc * STAT_CHUNK + jj
        if j < w:
            if mask[i, j] != 0:
                mc = float(0.0)
                for k in range(nl):
                    g = intensity[k]
                    v = images[k, i, j]
                    if _grey(wp.vec3(v[0] * g[0], v[1] * g[1], v[2] * g[2])) > lit_level:
                        n_lit += 1.0
                    if wp.max(v[0] * g[0], wp.max(v[1] * g[1], v[2] * g[2])) >= saturation:
                        n_sat += 1.0
                    mc += _grey(v)
                grey += mc
                # the noise statistic on a sub-grid (every HF_STEP_I-th row, HF_STEP_J-th column): a
                # frame-level share needs no more samples, and the 3x3 ratio stencil is the costly part
                interior = i >= 1 and j >= 1 and i < h - 1 and j < w - 1 and i % HF_STEP_I == 0 and j % HF_STEP_J == 0
                if interior:
                    for di in range(-1, 2):
                        for dj in range(-1, 2):
                            if mask[i + di, j + dj] == 0:
                                interior = False
                            else:
                                s = float(0.0)
                                for k in range(nl):
                                    s += _grey(images[k, i + di, j + dj])
                                if s <= lit_level * float(nl):
                                    interior = False
                if interior:
                    wgt = mc / float(nl)
                    for k in range(nl):
                        lap = float(0.0)
                        for di in range(-1, 2):
                            for dj in range(-1, 2):
                                c = float(1.0)
                                if di == 0:
                                    c = c * 2.0
                                if dj == 0:
                                    c = c * 2.0
                                if (di + dj) % 2 != 0:
                                    c = -c
                                s = float(0.0)
                                for l in range(nl):
                                    s += _grey(images[l, i + di, j + dj])
                                lap += c * float(nl) * _grey(images[k, i + di, j + dj]) / s
                        hf += wgt * wp.abs(lap)
                    hf_grey += wgt * float(nl)
    slot = (i * ncol + jc) % STAT_SLOTS
    if n_lit > 0.0:
        wp.atomic_add(stats, slot, STAT_LIT, n_lit)
    if n_sat > 0.0:
        wp.atomic_add(stats, slot, STAT_SATURATED, n_sat)
    if grey > 0.0:
        wp.atomic_add(stats, slot, STAT_GREY, grey)
    if hf_grey > 0.0:
        wp.atomic_add(stats, slot, STAT_HF, hf)
        wp.atomic_add(stats, slot, STAT_HF_GREY, hf_grey)


@wp.kernel(enable_backward=False)
def residual_sum(residual: wp.array2d(dtype=wp.float32), mask: wp.array2d(dtype=wp.uint8),
                 flags: wp.array2d(dtype=wp.int32), stats: wp.array2d(dtype=wp.float32)):
    """stats[:, STAT_RESIDUAL] += the residual summed over the mask pixels the solve determined (no
    ``FLAG_FEW_OBSERVATIONS``: 3 or more valid observations), stats[:, STAT_DETERMINED] += their count (slotted).
    One thread per ``STAT_CHUNK`` pixels of a row (columns ``jc``, ``jc + ceil(W / STAT_CHUNK)``, ...), as
    :func:`frame_stats`: launch over (H, ceil(W / STAT_CHUNK)).  (One thread and two atomics a pixel cost
    0.069 ms at 1024^2 on an H200, this form 0.019.)

    An under-determined pixel's residual says nothing about the model: one with no lit observation (a dark
    background, an attached shadow under every light) borrows its neighbours' albedo and so "misfits" its
    black observations by whatever that albedo predicts."""
    i, jc = wp.tid()
    w = mask.shape[1]
    ncol = (w + STAT_CHUNK - 1) // STAT_CHUNK
    total = float(0.0)
    count = float(0.0)
    for jj in range(STAT_CHUNK):
        j = jj * ncol + jc
        if j < w:
            if mask[i, j] != 0 and (flags[i, j] & FLAG_FEW_OBSERVATIONS) == 0:
                total += residual[i, j]
                count += 1.0
    if count > 0.0:
        slot = (i * ncol + jc) % STAT_SLOTS
        wp.atomic_add(stats, slot, STAT_RESIDUAL, total)
        wp.atomic_add(stats, slot, STAT_DETERMINED, count)


@wp.kernel(enable_backward=False)
def mark_jumps(residual: wp.array2d(dtype=wp.float32), previous: wp.array2d(dtype=wp.float32),
               mask: wp.array2d(dtype=wp.uint8), threshold: wp.array(dtype=wp.float32), factor: float,
               redo: wp.array2d(dtype=wp.uint8), stats: wp.array2d(dtype=wp.float32)):
    """redo[i, j] = 1 where a warm-started pixel's residual jumped: above ``factor`` times its residual in the
    last accepted frame (``previous``) and above ``threshold[0]``.

    The host sets the threshold from the running levels of the accepted frames
    (0 before the first: nothing is marked); it lives on the device so that a
    captured graph reads the current value.  Pixels that always fit poorly
    (rims, cast shadows) do not jump, so they are not re-solved every frame.
    Counts the marked pixels in ``stats[:, STAT_REDONE]``.
    """
    i, j = wp.tid()
    r = wp.uint8(0)
    if mask[i, j] != 0 and threshold[0] > 0.0:
        if residual[i, j] > wp.max(threshold[0], factor * previous[i, j]):
            r = wp.uint8(1)
            wp.atomic_add(stats, (i * mask.shape[1] + j) % STAT_SLOTS, STAT_REDONE, 1.0)
    redo[i, j] = r


@wp.kernel(enable_backward=False)
def refresh_rows(mask: wp.array2d(dtype=wp.uint8), phase: wp.array(dtype=wp.int32), period: int,
                 residual: wp.array2d(dtype=wp.float32), threshold: wp.array(dtype=wp.float32), misfits: int,
                 floor: wp.array2d(dtype=wp.float32), rows: wp.array2d(dtype=wp.uint8)):
    """rows[i, j] = 1 inside the mask on the rows ``i = phase[0] (mod period)``: this frame's share of the
    rolling cold re-solve (whole rows, so that a GPU warp's threads are all busy or all idle).

    ``misfits`` 1: only the pixels of those rows whose residual exceeds ``threshold[0]`` (the jump test's
    running level; none before it is set) and ``RETRY_FLOOR_FACTOR`` times ``floor`` (the residual the
    pixel kept after its last cold re-solve, 0 for none: :func:`keep_better`), so that a pixel a warm start
    keeps in a wrong basin gets a cold retry every ``period`` frames at the cost of the misfits alone, and a
    pixel whose cold multi-start solve found nothing better (its misfit is the model's or the data's, not a
    basin's) is not solved again until its residual rises."""
    i, j = wp.tid()
    r = wp.uint8(0)
    if mask[i, j] != 0 and i % period == phase[0] % period:
        if misfits == 0:
            r = wp.uint8(1)
        elif threshold[0] > 0.0 and residual[i, j] > wp.max(threshold[0], RETRY_FLOOR_FACTOR * floor[i, j]):
            r = wp.uint8(1)
    rows[i, j] = r


@wp.kernel(enable_backward=False)
def save_rows(rows: wp.array2d(dtype=wp.uint8), normals: wp.array2d(dtype=wp.vec3), albedo: wp.array2d(dtype=wp.vec3),
              residual: wp.array2d(dtype=wp.float32), flags: wp.array2d(dtype=wp.int32),
              normals0: wp.array2d(dtype=wp.vec3), albedo0: wp.array2d(dtype=wp.vec3),
              residual0: wp.array2d(dtype=wp.float32), flags0: wp.array2d(dtype=wp.int32)):
    """The warm solution of the pixels ``rows`` marks, saved into ``*0`` before their cold re-solve (what
    :func:`keep_better` reads; other pixels are not touched)."""
    i, j = wp.tid()
    if rows[i, j] != 0:
        normals0[i, j] = normals[i, j]
        albedo0[i, j] = albedo[i, j]
        residual0[i, j] = residual[i, j]
        flags0[i, j] = flags[i, j]


@wp.kernel(enable_backward=False)
def advance_phase(phase: wp.array(dtype=wp.int32), period: int, step: int):
    """The next frame's rows of the rolling re-solve (dim 1; on the device, so a captured graph advances it):
    ``step`` 1 forward, ``period - 1`` back (a rejected frame's advance undone)."""
    phase[0] = (phase[0] + step) % period


@wp.kernel(enable_backward=False)
def keep_better(rows: wp.array2d(dtype=wp.uint8), normals0: wp.array2d(dtype=wp.vec3),
                albedo0: wp.array2d(dtype=wp.vec3), residual0: wp.array2d(dtype=wp.float32),
                flags0: wp.array2d(dtype=wp.int32), few: int, take_few: int, normals: wp.array2d(dtype=wp.vec3),
                albedo: wp.array2d(dtype=wp.vec3), residual: wp.array2d(dtype=wp.float32),
                flags: wp.array2d(dtype=wp.int32), floor: wp.array2d(dtype=wp.float32)):
    """Where ``rows`` is set, keep the cold re-solve only when it ranks better than the warm solution saved in
    ``*0`` (a lower residual on a pixel without the ``few`` flag bit: :func:`gpps.host.merge.ranks_better`);
    otherwise restore the warm one.  With ``take_few`` (the sweep after a change of the material) an
    under-determined pixel (the ``few`` bit) takes the cold re-solve: its residual cannot rank the two, and its
    warm start came from a solve under the old material, the cold multi-start solve from none.  ``floor``
    takes the kept residual (what :func:`refresh_rows` compares a misfit with)."""
    i, j = wp.tid()
    if rows[i, j] != 0:
        better = residual[i, j] < residual0[i, j] and (flags[i, j] & few) == 0
        if take_few != 0 and (flags[i, j] & few) != 0:
            better = True
        if not better:
            normals[i, j] = normals0[i, j]
            albedo[i, j] = albedo0[i, j]
            residual[i, j] = residual0[i, j]
            flags[i, j] = flags0[i, j]
        floor[i, j] = residual[i, j]

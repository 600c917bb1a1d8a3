"""DGMC's regions and geodesic candidates on the device (seed 4.1.9): connected-region labels, outer boundaries and
the ``K`` nearest boundary pixels of every highlight pixel by geodesic distance, as Warp kernels (launched by
:class:`gpps.pipeline.dgmc.DeviceDGMC`; why the min-plus sweeps give Dijkstra's lists exactly is written in
:mod:`gpps.kernels.dgmc`)."""

import warp as wp

SQRT2 = wp.constant(wp.float64(1.4142135623730951))
STEP_UNIT = wp.constant(65536)  # one unit step in the packed (a << 16) | b distance
STEP_DIAG = wp.constant(1)  # one diagonal step
NO_KEY = wp.constant(2147483647)

vec8i = wp.types.vector(length=8, dtype=wp.int32)
vec8d = wp.types.vector(length=8, dtype=wp.float64)
# the 8 neighbour offsets in raster order (the order of the slots of geodesic_slots_kernel / geodesic_relax_kernel)
OFF_I = wp.constant(vec8i(-1, -1, -1, 0, 0, 1, 1, 1))
OFF_J = wp.constant(vec8i(-1, 0, 1, -1, 1, -1, 0, 1))


# --------------------------------------------------------------------------- regions and boundaries


@wp.func
def is_neighbour(di: int, dj: int, conn: int) -> bool:
    """(di, dj) != (0, 0) is a neighbour offset under 4- or 8-connectivity."""
    if di == 0 and dj == 0:
        return False
    if conn == 4 and di != 0 and dj != 0:
        return False
    return True


@wp.kernel
def label_init_kernel(region: wp.array2d(dtype=wp.uint8), labels: wp.array2d(dtype=wp.int32)):
    """labels = flat index on region pixels, -1 elsewhere."""
    i, j = wp.tid()
    if region[i, j] != wp.uint8(0):
        labels[i, j] = i * region.shape[1] + j
    else:
        labels[i, j] = -1


@wp.kernel
def label_min_kernel(region: wp.array2d(dtype=wp.uint8), conn: int, labels: wp.array2d(dtype=wp.int32),
                     changed: wp.array(dtype=wp.int32)):
    """One in-place min-label step with pointer jumping: labels only decrease and always name a pixel of the same
    component, so concurrent updates are safe; the fixed point is each component's first (raster) pixel."""
    i, j = wp.tid()
    if region[i, j] == wp.uint8(0):
        return
    h = region.shape[0]
    w = region.shape[1]
    cur = labels[i, j]
    best = cur
    for di in range(-1, 2):
        for dj in range(-1, 2):
            if is_neighbour(di, dj, conn):
                a = i + di
                b = j + dj
                if a >= 0 and a < h and b >= 0 and b < w and region[a, b] != wp.uint8(0):
                    best = wp.min(best, labels[a, b])
    best = wp.min(best, labels[best // w, best % w])
    if best < cur:
        labels[i, j] = best
        wp.atomic_add(changed, 0, 1)


@wp.kernel
def roots_kernel(labels: wp.array2d(dtype=wp.int32), roots: wp.array(dtype=wp.int32)):
    """roots[flat] = 1 where the pixel is its component's first pixel."""
    i, j = wp.tid()
    idx = i * labels.shape[1] + j
    roots[idx] = wp.where(labels[i, j] == idx, 1, 0)


@wp.kernel
def label_number_kernel(numbers: wp.array(dtype=wp.int32), labels: wp.array2d(dtype=wp.int32)):
    """labels = 1..n in the order of the components' first pixels (scipy.ndimage.label's), 0 off the region."""
    i, j = wp.tid()
    lab = labels[i, j]
    if lab < 0:
        labels[i, j] = 0
    else:
        labels[i, j] = numbers[lab]


@wp.kernel
def boundary_kernel(mask: wp.array2d(dtype=wp.uint8), region: wp.array2d(dtype=wp.uint8),
                    labels: wp.array2d(dtype=wp.int32), conn: int, boundary: wp.array2d(dtype=wp.int32)):
    """Outer-boundary pixels (in the mask, off the region, next to it) labelled with the smallest adjacent region."""
    i, j = wp.tid()
    h = mask.shape[0]
    w = mask.shape[1]
    best = int(0)
    if mask[i, j] != wp.uint8(0) and region[i, j] == wp.uint8(0):
        for di in range(-1, 2):
            for dj in range(-1, 2):
                if is_neighbour(di, dj, conn):
                    a = i + di
                    b = j + dj
                    if a >= 0 and a < h and b >= 0 and b < w and labels[a, b] > 0:
                        if best == 0 or labels[a, b] < best:
                            best = labels[a, b]
    boundary[i, j] = best


# --------------------------------------------------------------------------- geodesic K-nearest boundary pixels


@wp.func
def key_value(key: int) -> wp.float64:
    """Length ``a + b sqrt(2)`` of a packed ``(a << 16) | b`` step count."""
    return wp.float64(key >> 16) + wp.float64(key & 65535) * SQRT2


@wp.func
def key_less(ka: int, sa: int, kb: int, sb: int) -> bool:
    """(distance, source) order: shorter first, ties to the smaller flat source index."""
    va = key_value(ka)
    vb = key_value(kb)
    if va < vb:
        return True
    if va > vb:
        return False
    return sa < sb


@wp.func
def borders(mask: wp.array2d(dtype=wp.uint8), region: wp.array2d(dtype=wp.uint8), labels: wp.array2d(dtype=wp.int32),
            conn: int, a: int, b: int, lab: int) -> bool:
    """Pixel (a, b) is on the outer boundary of region ``lab`` (in the mask, off the region, conn-adjacent to it)."""
    h = mask.shape[0]
    w = mask.shape[1]
    if mask[a, b] == wp.uint8(0) or region[a, b] != wp.uint8(0):
        return False
    for di in range(-1, 2):
        for dj in range(-1, 2):
            if is_neighbour(di, dj, conn):
                c = a + di
                d = b + dj
                if c >= 0 and c < h and d >= 0 and d < w and labels[c, d] == lab:
                    return True
    return False


@wp.kernel(enable_backward=False)
def geodesic_slots_kernel(mask: wp.array2d(dtype=wp.uint8), region: wp.array2d(dtype=wp.uint8),
                          labels: wp.array2d(dtype=wp.int32), conn: int, slots: wp.array2d(dtype=wp.int32)):
    """The kinds of the 8 neighbour slots of every region pixel, once before the sweeps (they depend only on the
    labels): bits ``2 sl, 2 sl + 1`` of ``slots[i, j]`` hold slot ``sl``'s kind (raster order of OFF_I / OFF_J):
    1 = a list (same region), 2 = one direct source (a pixel on the region's outer boundary, :func:`borders`),
    0 = none; -1 off the region."""
    i, j = wp.tid()
    h = mask.shape[0]
    w = mask.shape[1]
    if region[i, j] == wp.uint8(0):
        slots[i, j] = -1
        return
    lab = labels[i, j]
    code = int(0)
    for sl in range(8):
        a = i + OFF_I[sl]
        b = j + OFF_J[sl]
        sk = int(0)
        if a >= 0 and a < h and b >= 0 and b < w:
            if labels[a, b] == lab:
                sk = 1
            elif borders(mask, region, labels, conn, a, b, lab):
                sk = 2
        code = code | (sk << (2 * sl))
    slots[i, j] = code


@wp.kernel(enable_backward=False)
def geodesic_relax_kernel(slots: wp.array2d(dtype=wp.int32), first: int,
                          old_key: wp.array3d(dtype=wp.int32), old_src: wp.array3d(dtype=wp.int32),
                          prev_changed: wp.array2d(dtype=wp.int32),
                          new_key: wp.array3d(dtype=wp.int32), new_src: wp.array3d(dtype=wp.int32),
                          changed: wp.array2d(dtype=wp.int32), count: wp.array(dtype=wp.int32), row0: int,
                          part: int):
    """One Jacobi min-plus sweep of the K-nearest-boundary lists (module docstring).

    A region pixel none of whose 3x3 neighbourhood (itself included) changed in the previous sweep (and not the
    first sweep) is skipped: its list cannot change.  Nothing is copied between sweeps: the stage swaps ``old`` and
    ``new`` (ping-pong), and a skipped pixel's ``new`` already holds its current list, because it did not change
    in the previous sweep (``new`` holds the list of two sweeps ago, equal to the last one).

    Args:
        slots: (H, W) neighbour slot kinds from :func:`geodesic_slots_kernel`, -1 off the region.
        old_key, old_src: (H, W, K) lists of the previous sweep, nearest first: packed step counts and flat source
            indices (``row * W + column``); -1 sources (and NO_KEY) past the end.
        new_key, new_src: (H, W, K) out.
        changed: (H, W) out: 1 where the list changed; count[part] += their number.
        row0: first row of this launch (dim (rows, W)); a CPU launch split by rows across threads
            (gpps.pipeline.cpu_threads) gives each part its own slot ``part`` of ``count``.
    """
    t, j = wp.tid()
    i = t + row0
    h = slots.shape[0]
    w = slots.shape[1]
    kk = old_key.shape[2]
    changed[i, j] = 0
    code = slots[i, j]
    if code < 0:
        return
    if first == 0:
        act = int(0)
        for di in range(-1, 2):
            for dj in range(-1, 2):
                a = i + di
                b = j + dj
                if a >= 0 and a < h and b >= 0 and b < w and prev_changed[a, b] != 0:
                    act = 1
        if act == 0:
            return
    # the 8 neighbour slots: 1 = a list (same region), 2 = one direct source (a boundary pixel), 0 = none
    slot = vec8i()
    head = vec8i()
    step = vec8i()
    for sl in range(8):
        slot[sl] = (code >> (2 * sl)) & 3
        if OFF_I[sl] != 0 and OFF_J[sl] != 0:
            step[sl] = STEP_DIAG
        else:
            step[sl] = STEP_UNIT
    # the current head of each slot (value, packed key, source; -1: exhausted), refreshed only when popped
    hval = vec8d()
    hkey = vec8i()
    hsrc = vec8i()
    for sl in range(8):
        a = i + OFF_I[sl]
        b = j + OFF_J[sl]
        hsrc[sl] = -1
        if slot[sl] == 1:
            cs = old_src[a, b, 0]
            if cs >= 0:
                hsrc[sl] = cs
                hkey[sl] = old_key[a, b, 0] + step[sl]
        elif slot[sl] == 2:
            hsrc[sl] = a * w + b
            hkey[sl] = step[sl]
        if hsrc[sl] >= 0:
            hval[sl] = key_value(hkey[sl])
    cnt = int(0)
    while cnt < kk:
        best = int(-1)
        for sl in range(8):
            if hsrc[sl] >= 0:
                if best < 0:
                    best = sl
                elif hval[sl] < hval[best] or (hval[sl] == hval[best] and hsrc[sl] < hsrc[best]):
                    best = sl
        if best < 0:
            break
        bkey = hkey[best]
        bsrc = hsrc[best]
        # advance the popped slot
        hsrc[best] = -1
        if slot[best] == 1:
            nh = head[best] + 1
            head[best] = nh
            if nh < kk:
                a = i + OFF_I[best]
                b = j + OFF_J[best]
                cs = old_src[a, b, nh]
                if cs >= 0:
                    hsrc[best] = cs
                    hkey[best] = old_key[a, b, nh] + step[best]
                    hval[best] = key_value(hkey[best])
        dup = int(0)
        for t in range(cnt):
            if new_src[i, j, t] == bsrc:
                dup = 1
        if dup == 0:
            new_key[i, j, cnt] = bkey
            new_src[i, j, cnt] = bsrc
            cnt += 1
    for t in range(cnt, kk):
        new_key[i, j, t] = NO_KEY
        new_src[i, j, t] = -1
    diff = int(0)
    for t in range(kk):
        if new_src[i, j, t] != old_src[i, j, t] or new_key[i, j, t] != old_key[i, j, t]:
            diff = 1
    if diff != 0:
        changed[i, j] = 1
        wp.atomic_add(count, part, 1)


@wp.kernel
def list_reset_kernel(keys: wp.array3d(dtype=wp.int32), srcs: wp.array3d(dtype=wp.int32),
                      changed: wp.array2d(dtype=wp.int32)):
    """Empty lists (NO_KEY, -1) and no change marks."""
    i, j, t = wp.tid()
    keys[i, j, t] = NO_KEY
    srcs[i, j, t] = -1
    if t == 0:
        changed[i, j] = 0


@wp.kernel
def key_distance_kernel(keys: wp.array3d(dtype=wp.int32), srcs: wp.array3d(dtype=wp.int32),
                        dist: wp.array3d(dtype=wp.float64)):
    """dist = a + b sqrt(2) of each list entry, +inf past the end."""
    i, j, t = wp.tid()
    if srcs[i, j, t] < 0:
        dist[i, j, t] = wp.float64(wp.inf)
    else:
        dist[i, j, t] = key_value(keys[i, j, t])

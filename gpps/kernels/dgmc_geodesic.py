"""DGMC's regions and geodesic candidates on the device (seed 4.1.9): connected-region labels, outer boundaries and
the ``K`` nearest boundary pixels of every highlight pixel by geodesic distance, as Warp kernels (launched by
:class:`gpps.pipeline.dgmc.DeviceDGMC`; why the min-plus sweeps give Dijkstra's lists exactly is written in
:mod:`gpps.kernels.dgmc`)."""

import warp as wp

SQRT2 = wp.constant(wp.float64(1.4142135623730951))
STEP_UNIT = wp.constant(65536)  # one unit step in the packed (a << 16) | b distance
STEP_DIAG = wp.constant(1)  # one diagonal step
NO_KEY = wp.constant(2147483647)
LIST_CAP = wp.constant(32)  # sources of the list being merged kept in a thread-local set (the default K = 32)

vec8i = wp.types.vector(length=8, dtype=wp.int32)
vec8l = wp.types.vector(length=8, dtype=wp.int64)
SRC_BITS = wp.constant(28)  # flat source indices below 2^28 in a merge head (DeviceDGMC checks H W)
SRC_MASK = wp.constant(wp.int64((1 << SRC_BITS) - 1))
NO_HEAD = wp.constant(wp.int64(9223372036854775807))  # an exhausted merge slot (after every real head)
# the 8 neighbour offsets in raster order (the slots of geodesic_slots_kernel and geodesic_relax_kernel)
OFF_I = wp.constant(vec8i(-1, -1, -1, 0, 0, 1, 1, 1))
OFF_J = wp.constant(vec8i(-1, 0, 1, -1, 1, -1, 0, 1))
# the packed step of each slot: diagonal or unit
STEPS = wp.constant(vec8i(STEP_DIAG, STEP_UNIT, STEP_DIAG, STEP_UNIT, STEP_UNIT, STEP_DIAG, STEP_UNIT, STEP_DIAG))
# the thread-local set of the sources taken by the merge: open addressing with linear probing, entries
# source + 1 (0 = empty), 2 LIST_CAP slots (at most half full, so a probe ends at the source or an empty slot)
TAB_BITS = wp.constant(6)
TAB_SIZE = wp.constant(64)
HASH_MUL = wp.constant(wp.uint32(2654435761))  # Knuth's multiplicative hash (2^32 / golden ratio)
vectab = wp.types.vector(length=TAB_SIZE, dtype=wp.int32)


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
def head_order(key: int, src: int) -> wp.int64:
    """One int64 whose order is the (distance, source) order of merge heads (shorter first, ties to the smaller
    flat source index): ``floor((a + b sqrt 2) 2^18)`` above the source's SRC_BITS bits, so the best of 8 heads is
    one integer comparison each.

    Why the order is exact: two different counts of the packed range (a < 2^15, b < 2^16) differ in length by
    ``|da - db sqrt 2| = |da^2 - 2 db^2| / (|da| + |db| sqrt 2) >= 1 / (2^15 + 2^16 sqrt 2) > 2^-17`` (the
    numerator is a non-zero integer: sqrt 2 is irrational), i.e. by more than 2 after the scaling; the scaled float64
    length (< 2^35) is off by less than 1e-4, so the floors keep the lengths' order, and equal counts give equal
    floors (the source decides, as in the float64 comparison of the host).  35 + 28 bits fit an int64."""
    return (wp.int64(wp.floor(key_value(key) * wp.float64(262144.0))) << wp.int64(SRC_BITS)) | wp.int64(src)


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
        new_key, new_src: (H, W, K) out.  Any K works: past LIST_CAP entries the repeat check reads new_src.
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
    # the current head of each slot: its (distance, source) order as one int64 (head_order), its packed key and
    # its position in the neighbour's list; an exhausted slot holds NO_HEAD, which every live head precedes
    hcmp = vec8l()
    hkey = vec8i()
    head = vec8i()
    for sl in range(8):
        kind = (code >> (2 * sl)) & 3
        a = i + OFF_I[sl]
        b = j + OFF_J[sl]
        hcmp[sl] = NO_HEAD
        hkey[sl] = NO_KEY
        if kind == 1:
            cs = old_src[a, b, 0]
            if cs >= 0:
                hkey[sl] = old_key[a, b, 0] + STEPS[sl]
                hcmp[sl] = head_order(hkey[sl], cs)
        elif kind == 2:
            hkey[sl] = STEPS[sl]
            hcmp[sl] = head_order(hkey[sl], a * w + b)
            head[sl] = kk  # one entry only
    # merge: pop the smallest (distance, source) head, skip a source already taken (each neighbour list holds a
    # source once, so a repeat comes from another slot, later and not nearer: the first pop of a source is its
    # distance).  The first LIST_CAP sources taken are kept in a thread-local set (any beyond are looked up in
    # new_src); a slot's next entry whose source is already in the set is passed over when the slot is
    # refreshed (the set only grows, so it could only be popped as a repeat), which skips most repeats before
    # the best-head scan.  Each entry is written once and compared with the old list's entry in the same pass.
    taken = vectab()
    cnt = int(0)
    diff = int(0)
    while cnt < kk:
        best = int(0)
        for sl in range(1, 8):
            if hcmp[sl] < hcmp[best]:
                best = sl
        bcmp = hcmp[best]
        if bcmp == NO_HEAD:
            break
        bsrc = int(bcmp & SRC_MASK)
        bkey = hkey[best]
        # advance the popped slot
        nh = head[best] + 1
        hcmp[best] = NO_HEAD
        hkey[best] = NO_KEY
        a = i + OFF_I[best]
        b = j + OFF_J[best]
        while nh < kk:
            cs = old_src[a, b, nh]
            if cs < 0:
                break
            # cs in the set? (linear probing from its hash; inlined: a wp.func would get the set by value)
            ph = int((wp.uint32(cs) * HASH_MUL) >> wp.uint32(32 - TAB_BITS))
            while taken[ph] != 0 and taken[ph] != cs + 1:
                ph = (ph + 1) & (TAB_SIZE - 1)
            if taken[ph] == 0:
                hkey[best] = old_key[a, b, nh] + STEPS[best]
                hcmp[best] = head_order(hkey[best], cs)
                break
            nh += 1
        head[best] = nh
        dup = int(0)
        hh = int((wp.uint32(bsrc) * HASH_MUL) >> wp.uint32(32 - TAB_BITS))
        while taken[hh] != 0 and taken[hh] != bsrc + 1:
            hh = (hh + 1) & (TAB_SIZE - 1)
        if taken[hh] != 0:
            dup = 1
        for t in range(LIST_CAP, cnt):
            if new_src[i, j, t] == bsrc:
                dup = 1
        if dup == 0:
            if cnt < LIST_CAP:
                taken[hh] = bsrc + 1
            new_key[i, j, cnt] = bkey
            new_src[i, j, cnt] = bsrc
            if old_src[i, j, cnt] != bsrc or old_key[i, j, cnt] != bkey:
                diff = 1
            cnt += 1
    for t in range(cnt, kk):
        new_key[i, j, t] = NO_KEY
        new_src[i, j, t] = -1
        if old_src[i, j, t] != -1 or old_key[i, j, t] != NO_KEY:
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

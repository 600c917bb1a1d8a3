"""Float64 sums reduced per CUDA block in shared memory, one atomic a block (Taichi device helpers).

A parallel Taichi loop that adds every pixel's term into one element of a field
(``sc[k] += v``) leaves one float64 atomic per pixel on one address on CUDA:
Taichi keeps such sums thread-local only for 0-D fields, and its warp
reductions do not cover float64, so the atomics serialise (77-148 us a loop on
40 670 pixels on an H100, see :mod:`gpps.kernels.bini`).  The block form: the
loop runs over the pixel count rounded up to whole blocks of :data:`BLOCK`
threads (``ti.loop_config(block_dim=BLOCK)``, padding threads add 0), each
thread writes its float64 term into a shared array, the block tree-sums it and
thread 0 adds the block's total with one atomic::

    ti.loop_config(block_dim=BLOCK)
    for k in range(whole_blocks(n)):
        pad = ti.simt.block.SharedArray((BLOCK,), ti.f64)
        v = ti.cast(0, ti.f64)
        if k < n:
            v = ...  # this thread's term, widened to float64 before it is stored
        block_add(pad, k, v, dst, idx)

Every thread of a block must reach :func:`block_total` (it synchronises the
block), so the padding threads run it too and the loop's range is a multiple of
``BLOCK`` (Taichi's grid-stride loop then keeps each block's threads together).
Shared arrays exist on CUDA only: Taichi's CPU backend refuses them ("not
supported for arch x64"), so the CPU builds keep their own sums.

Only device code lives here.
"""

from gpps._taichi import ti

BLOCK = 128  # threads of a block in the block-sum builds (a power of two)
_LOG_BLOCK = BLOCK.bit_length() - 1


@ti.func
def whole_blocks(n):
    """``n`` rounded up to a multiple of :data:`BLOCK` (the range of a block-sum loop over ``n`` items)."""
    return (n + BLOCK - 1) // BLOCK * BLOCK


@ti.func
def block_total(pad: ti.template(), tid):
    """Tree sum of the block's ``pad[0..BLOCK)`` into ``pad[0]`` (every thread of the block must call it)."""
    ti.simt.block.sync()
    for k in ti.static(range(_LOG_BLOCK)):
        stride = ti.static(BLOCK >> (k + 1))
        if tid < stride:
            pad[tid] += pad[tid + stride]
        ti.simt.block.sync()


@ti.func
def block_total2(pa: ti.template(), pb: ti.template(), tid):
    """:func:`block_total` of two shared arrays in one tree (the same additions in the same order for each,
    half the block barriers of two trees)."""
    ti.simt.block.sync()
    for k in ti.static(range(_LOG_BLOCK)):
        stride = ti.static(BLOCK >> (k + 1))
        if tid < stride:
            pa[tid] += pa[tid + stride]
            pb[tid] += pb[tid + stride]
        ti.simt.block.sync()


@ti.func
def block_add(pad: ti.template(), k, v, dst: ti.template(), idx: ti.template()):
    """``dst[idx] += `` the sum of the block's float64 terms ``v`` (thread ``k`` of the loop; every thread
    of the block must call it): ``v`` into the shared array ``pad``, :func:`block_total`, one atomic."""
    tid = k % BLOCK
    pad[tid] = v
    block_total(pad, tid)
    if tid == 0:
        ti.atomic_add(dst[idx], pad[0])


def make_acc_sums(acc, bd: int, cuda: bool):
    """The ti.funcs ``red(pad, tid, v, idx)`` (``acc[idx] +=`` the block's sum of ``v``) and
    ``red2(pa, pb, tid, va, ia, vb, ib)`` (two sums in one block tree) of a persistent task of blocks of ``bd``
    threads (every thread of a block calls them; ``pad``, ``pa``, ``pb``: its shared arrays of :data:`BLOCK`
    float64).  Off CUDA (one thread, no shared arrays) they add ``v`` directly.  Used by BiNI's persistent IRLS
    and the integrator's persistent PCG."""

    @ti.func
    def red(pad: ti.template(), tid, v, idx):
        if ti.static(cuda):
            t = tid % bd
            pad[t] = v
            block_total(pad, t)
            if t == 0:
                ti.atomic_add(acc[idx], pad[0])
        else:
            acc[idx] += v

    @ti.func
    def red2(pa: ti.template(), pb: ti.template(), tid, va, ia, vb, ib):
        if ti.static(cuda):
            t = tid % bd
            pa[t] = va
            pb[t] = vb
            block_total2(pa, pb, t)
            if t == 0:
                ti.atomic_add(acc[ia], pa[0])
                ti.atomic_add(acc[ib], pb[0])
        else:
            acc[ia] += va
            acc[ib] += vb

    return red, red2

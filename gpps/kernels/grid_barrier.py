"""A software grid barrier for persistent Taichi tasks on CUDA (device code only).

A persistent task runs ``nblocks x bd`` threads, every block resident at once,
whose phases meet at grid barriers: each block arrives with one atomic on a
counter and waits until the counter reaches ``gen * nblocks``; grid memory
fences on both sides order the phases' global writes and reads.

The wait is *warp-uniform*: the whole first warp of the block runs the polling
loop, lane 0 reads the counter with an atomic and broadcasts it with a warp
shuffle, so every lane leaves the loop in the same iteration.  The earlier form
(lane 0 alone spinning while the rest of its warp waited at the block barrier)
is a warp diverged around a loop at an aligned ``bar.sync``: with Taichi's LLVM
code it deadlocked on an H100 for some kernels (two barriers in a row, or a
block reduction before one: perf/_dbg notes in the commit) and not others.

A block that polls more than ``LIMIT`` times sets ``bar[1]``, and every waiter
gives up at its next check (every 1024 polls): a GPU that cannot hold all the
blocks finishes with wrong values instead of hanging, and the caller, which
reads ``bar[1]`` after a kernel's first launch, falls back.
"""

from gpps._taichi import ti

LIMIT = 1 << 20  # polls before a grid barrier gives up (a block that never became resident)
WARP = 32


def make_gsync(bar, nblocks: int, bd: int, cuda: bool = True):
    """The ti.func ``gsync(tid, gen)`` of a task of ``nblocks x bd`` threads.

    Args:
        bar: i32 field of length 2: ``bar[0]`` the arrival counter (zeroed at the launch, before the
            persistent loop), ``bar[1]`` the timeout flag.
        nblocks: blocks of the task.
        bd: threads per block (a multiple of 32).
        cuda: the CUDA barrier; False: the one-thread build's stand-in (``nblocks = bd = 1``: the phases run
            in order, nothing to wait for), with which the persistent kernels test their arithmetic off CUDA.

    Returns:
        ``gsync(tid, gen)``: grid barrier number ``gen`` (1, 2, ... within a launch) for the thread of
        loop index ``tid``; returns ``gen + 1``.  Every thread of the task must call it.
    """
    if not cuda:
        if nblocks * bd != 1:
            raise ValueError(f"nblocks, bd: off CUDA a persistent task runs as one thread (1, 1), "
                             f"got ({nblocks}, {bd})")

        @ti.func
        def serial(tid, gen):  # one thread: the phases are in order
            return gen + 1

        return serial
    if bd % WARP:
        raise ValueError(f"bd: expected a multiple of {WARP} threads per block, got {bd}")

    @ti.func
    def gsync(tid, gen):
        ti.simt.grid.memfence()
        ti.simt.block.sync()
        lane = tid % bd
        if lane < WARP:  # the block's first warp, whole: it polls in step
            if lane == 0:
                ti.atomic_add(bar[0], 1)
            target = gen * nblocks
            polls = 0
            while True:
                v = 0
                if lane == 0:
                    v = ti.atomic_or(bar[0], 0)
                v = ti.simt.warp.shfl_sync_i32(ti.u32(0xFFFFFFFF), v, 0)
                if v >= target:
                    break
                polls += 1
                if polls % 1024 == 0:
                    f = 0
                    if lane == 0:
                        if polls >= LIMIT:
                            ti.atomic_or(bar[1], 1)
                        f = ti.atomic_or(bar[1], 0)
                    f = ti.simt.warp.shfl_sync_i32(ti.u32(0xFFFFFFFF), f, 0)
                    if f != 0:
                        break
        ti.simt.block.sync()
        ti.simt.grid.memfence()
        return gen + 1

    return gsync

"""RON's material search on the device: Nelder-Mead's step and the trimmed energy, as Warp kernels.

Device math only; the stage :class:`gpps.pipeline.material_search.NelderMeadSearch` owns the buffers and launches
these around :class:`gpps.pipeline.material.MaterialScorer`'s recorded solve, one pass per loop iteration
(a CUDA graph with a conditional while node on CUDA, so that the host does not wait for each step's energies).
A pass scores :data:`SEARCH_POINTS` = 4 candidates, whatever the dimension d <= 4:

* :func:`search_points_kernel` (one thread a candidate): in a step pass, from the sorted simplex ``sim``
  (``d + 1`` vertices in log-parameter space, best first), the reflection, expansion, outside and inside
  contraction of scipy's Nelder-Mead (coefficients 1, 2, 1/2, 1/2): every point the step may read, scored in
  one launch (the reflection decides which are read); in a shrink pass (the step before asked for a shrink,
  which is rare) the ``d`` vertices shrunk toward the best, ``sim[0] + 1/2 (sim[i] - sim[0])`` (the rest of
  the rows repeat the last).  Each point is clipped to the parameter bounds and written as a candidate
  material row (``exp`` of the log value into the lobe fields, the rest copied from ``base_row[0]``: the rows
  :meth:`MaterialScorer.lobe_candidates` packs).  Scoring the shrink points with every step instead would cost
  nothing on a latency-bound launch but 4 + d candidates: a cold multi-start launch of 6 x 2000 x 4 threads
  no longer fits one wave of the H100 at the solve's 216 registers a thread (4 x 2000 x 4 does);
* :func:`trimmed_rank_kernel`, :func:`trimmed_contrib_kernel`, :func:`trimmed_partial_kernel`,
  :func:`trimmed_energy_kernel`: each candidate's
  trimmed energy, the mean of the ``keep`` smallest squared residuals (:func:`gpps.pipeline.material.trimmed_energy`),
  without a sort: a sample value is kept when fewer than ``keep`` values precede it in the order (value, index),
  which keeps exactly the multiset a partition keeps (ties broken by index); its square (float64, exact for a
  float32 residual) is summed in a fixed order (strided partial sums, then the partials in order), so the energy
  does not depend on the launch's scheduling; only the summation order differs from numpy's (float64 rounding);
* :func:`search_step_kernel` (one thread): the Nelder-Mead decision on the scored points (or the shrink), the
  simplex update, the stable re-sort and the test ``max |sim[i] - sim[0]| <= xatol``; it counts the
  evaluations the method reads exactly as :meth:`gpps.flows.ron.RON._nelder_mead` does (``maxfev``: the search
  stops before a read past it) and clears the loop's condition when the search has converged or spent its budget.

A search uploaded without its simplex's energies starts with an *init* pass (phase 2, ``d + 1 <= 4``): the points
are the simplex's own vertices (clipped, as the host's scoring clips them; the rows past ``d`` repeat the last),
and the step kernel takes their energies as the simplex's, keeps vertex 0's (the start's) in ``f0``, sorts and
tests convergence, as the host does before an upload of a scored simplex: one host round trip less a search.

The trajectory is the host method's: the same points in the same float64 arithmetic, the same comparisons;
energies agree with the host's to float64 rounding of their sums, so a step can differ only where two energies
tie to ~1e-16 relative.
"""

import warp as wp

from gpps.kernels.brdf import MaterialParams

__all__ = ["search_points_kernel", "trimmed_rank_kernel", "trimmed_contrib_kernel", "trimmed_partial_kernel",
           "trimmed_energy_kernel", "RANK_SEGMENT",
           "search_step_kernel", "SEARCH_POINTS", "PARTIAL_LANES", "PHASE_STEP", "PHASE_SHRINK", "PHASE_INIT",
           "FIELD_KS", "FIELD_SHININESS", "FIELD_ROUGHNESS", "FIELD_ETA", "STATUS_RUNNING", "STATUS_CONVERGED",
           "STATUS_BUDGET"]

SEARCH_POINTS = 4  # candidates a pass: reflection, expansion, outside and inside contraction (or the d shrink points)
PARTIAL_LANES = 64  # strided partial sums per candidate of the trimmed energy
RANK_SEGMENT = 128  # sample values one thread of the rank kernel compares against (a P = 2000 row: 16 segments)
# lobe fields of MaterialParams a search parameter sets (gpps.pipeline.material._LOBE_FIELDS, eta: both)
FIELD_KS, FIELD_SHININESS, FIELD_ROUGHNESS, FIELD_ETA = 0, 1, 2, 3
STATUS_RUNNING, STATUS_CONVERGED, STATUS_BUDGET = 0, 1, 2
# state slots of the search: evaluations read, passes, status, phase (0: a step pass next, 1: a shrink pass,
# 2: the init pass, which scores the simplex itself)
STATE_NEED, STATE_PASSES, STATE_STATUS, STATE_PHASE = 0, 1, 2, 3
STATE_SIZE = 4
PHASE_STEP, PHASE_SHRINK, PHASE_INIT = 0, 1, 2


@wp.kernel(enable_backward=False)
def search_points_kernel(
    sim: wp.array2d(dtype=wp.float64),
    d: int,
    lo: wp.array(dtype=wp.float64),
    hi: wp.array(dtype=wp.float64),
    fields: wp.array(dtype=wp.int32),
    base_row: wp.array(dtype=MaterialParams),
    state: wp.array(dtype=wp.int32),
    cand: wp.array2d(dtype=wp.float64),
    mats: wp.array(dtype=MaterialParams),
):
    """Candidate ``c`` of the pass (4 threads): ``cand[c]`` (log space, inside ``[lo, hi]``) and its material row.

    Step pass: ``a xbar - b sim[d]`` with ``(a, b)`` = (2, 1), (3, 2), (1.5, 0.5), and ``0.5 xbar + 0.5 sim[d]``
    (``xbar``: the mean of the ``d`` best vertices, summed in vertex order as numpy does).  Shrink pass
    (``state[STATE_PHASE] == 1``): ``sim[0] + 0.5 (sim[i + 1] - sim[0])`` for ``c = i < d`` (the last one
    repeated above).  Each point is clipped to ``[lo, hi]`` and kept clipped (scipy's bounded Nelder-Mead: a point
    kept outside would be scored at its projection, a plateau the simplex could drift on); the material row scores
    ``exp(cand[c])``.  Init pass (``state[STATE_PHASE] == 2``): ``sim[c]`` itself (``c <= d``; the last vertex
    repeated above).
    """
    c = wp.tid()
    m = base_row[0]  # (a copy: the lobe fields set below do not touch the base row)
    one = wp.float64(1.0)
    rho = wp.float64(1.0)
    chi = wp.float64(2.0)
    psi = wp.float64(0.5)
    sigma = wp.float64(0.5)
    shrink = state[3] == 1
    init = state[3] == 2
    for j in range(d):
        x = wp.float64(0.0)
        if init:
            x = sim[wp.min(c, d), j]
        elif shrink:
            row = wp.min(c + 1, d)
            x = sim[0, j] + sigma * (sim[row, j] - sim[0, j])
        else:
            xbar = wp.float64(0.0)
            for i in range(d):
                xbar = xbar + sim[i, j]
            xbar = xbar / wp.float64(d)
            w = sim[d, j]
            if c == 0:
                x = (one + rho) * xbar - rho * w
            elif c == 1:
                x = (one + rho * chi) * xbar - rho * chi * w
            elif c == 2:
                x = (one + psi * rho) * xbar - psi * rho * w
            else:
                x = (one - psi) * xbar + psi * w
        x = wp.min(wp.max(x, lo[j]), hi[j])  # (scipy's bounded Nelder-Mead: the point itself is clipped)
        cand[c, j] = x
        v = wp.float32(wp.exp(x))
        f = fields[j]
        if f == 0:
            m.ks = v
        elif f == 1:
            m.shininess = v
        elif f == 2:
            m.roughness = v
        else:
            m.eta_u = v
            m.eta_v = v
    mats[c] = m


@wp.func
def _order_key(r: wp.float32) -> wp.float32:
    """A residual's sort key: NaN last (as numpy's partition puts it), else the value."""
    if wp.isnan(r):
        return wp.float32(wp.inf)
    return r


@wp.kernel(enable_backward=False)
def trimmed_rank_kernel(
    residual: wp.array2d(dtype=wp.float32),
    p: int,
    seg: int,
    before: wp.array2d(dtype=wp.int32),
):
    """``before[k, i] +=`` how many sample values of segment ``s`` of row ``k`` precede ``r[k, i]`` in the order
    (value, index): one thread a (candidate, pixel, segment), segment ``s`` the values ``[s seg, (s + 1) seg)``
    (the launch's third dimension covers the row), so that a launch of K x P pairs fills the GPU (one thread a
    pair with P compares each left 32 blocks on the H100's 132 SMs: 12 % achieved occupancy, 68-81 us) while
    the counts stay exact (integer atomics).  ``before`` must be zero on entry (:func:`trimmed_contrib_kernel`
    clears it after reading)."""
    k, i, s = wp.tid()
    ri = _order_key(residual[k, i])
    count = int(0)
    j0 = s * seg
    j1 = wp.min(j0 + seg, p)
    for j in range(j0, j1):
        rj = _order_key(residual[k, j])
        if rj < ri or (rj == ri and j < i):
            count += 1
    if count > 0:
        wp.atomic_add(before, k, i, count)


@wp.kernel(enable_backward=False)
def trimmed_contrib_kernel(
    residual: wp.array2d(dtype=wp.float32),
    keep: int,
    before: wp.array2d(dtype=wp.int32),
    contrib: wp.array2d(dtype=wp.float64),
):
    """``contrib[k, i]``: ``r[k, i]^2`` (float64) when fewer than ``keep`` sample values precede it (the counts of
    :func:`trimmed_rank_kernel`), else 0; the count is cleared for the next pass."""
    k, i = wp.tid()
    v = wp.float64(0.0)
    if before[k, i] < keep:
        r = wp.float64(residual[k, i])
        v = r * r
    contrib[k, i] = v
    before[k, i] = 0


@wp.kernel(enable_backward=False)
def trimmed_partial_kernel(
    contrib: wp.array2d(dtype=wp.float64),
    p: int,
    partial: wp.array2d(dtype=wp.float64),
):
    """``partial[k, t]``: the sum of ``contrib[k, i]`` over ``i = t, t + L, ...`` (``L`` the launch's second
    dimension), in index order."""
    k, t = wp.tid()
    lanes = partial.shape[1]
    s = wp.float64(0.0)
    i = t
    while i < p:
        s = s + contrib[k, i]
        i += lanes
    partial[k, t] = s


@wp.kernel(enable_backward=False)
def trimmed_energy_kernel(
    partial: wp.array2d(dtype=wp.float64),
    keep: int,
    energy: wp.array(dtype=wp.float64),
):
    """``energy[k]``: the partial sums of candidate ``k`` added in order, over ``keep``."""
    k = wp.tid()
    s = wp.float64(0.0)
    for t in range(partial.shape[1]):
        s = s + partial[k, t]
    energy[k] = s / wp.float64(keep)


@wp.func
def _take(sim: wp.array2d(dtype=wp.float64), fsim: wp.array(dtype=wp.float64), cand: wp.array2d(dtype=wp.float64),
          d: int, row: int, c: int, f: wp.float64):
    """The worst vertex ``sim[row]`` becomes candidate ``c`` with energy ``f``."""
    for j in range(d):
        sim[row, j] = cand[c, j]
    fsim[row] = f


@wp.func
def _after(a: wp.float64, b: wp.float64) -> bool:
    """Whether energy ``a`` sorts after ``b`` in numpy's order: larger, NaN after every number."""
    if wp.isnan(a):
        return not wp.isnan(b)
    return a > b


@wp.kernel(enable_backward=False)
def search_step_kernel(
    energy: wp.array(dtype=wp.float64),
    cand: wp.array2d(dtype=wp.float64),
    d: int,
    maxfev: int,
    xatol: wp.float64,
    sim: wp.array2d(dtype=wp.float64),
    fsim: wp.array(dtype=wp.float64),
    f0: wp.array(dtype=wp.float64),
    state: wp.array(dtype=wp.int32),
    cond: wp.array(dtype=wp.int32),
):
    """One pass of Nelder-Mead on the sorted simplex (one thread), :meth:`gpps.flows.ron.RON._nelder_mead`'s rules.

    The init pass (phase 2) takes the first ``d + 1`` energies as the simplex's (``f0[0]``: vertex 0's, the
    start's), then sorts and tests convergence as after a step.

    ``state``: [evaluations read, passes, status, phase].  A step pass decides from the reflection (and reads
    what it needs of the other three); a shrink it asks for sets the phase and leaves the simplex for the next
    pass, which scores the shrunk vertices and replaces them.  ``cond[0]`` is cleared (the loop ends) when the
    simplex has converged or a read would pass ``maxfev`` (the simplex is then left as it was: its best vertex is
    the result, as the host method returns it; a budget that ends inside a shrink leaves the best vertex too).
    """
    if cond[0] == 0:
        return
    need = state[0]
    state[1] = state[1] + 1
    last = d
    budget = int(0)
    if state[3] == 2:  # the init pass: the simplex's own energies (need counts them already)
        state[3] = 0
        for i in range(d + 1):
            fsim[i] = energy[i]
        f0[0] = energy[0]
    elif state[3] == 1:  # the shrink pass: the d shrunk vertices' energies
        state[3] = 0
        if need + d > maxfev:  # a read of the shrink passes the budget: the host keeps its best vertex
            need = maxfev
            budget = 1
        else:
            for i in range(1, d + 1):
                _take(sim, fsim, cand, d, i, i - 1, energy[i - 1])
            need += d
    elif need >= maxfev:
        budget = 1
    else:
        need += 1
        fxr = energy[0]
        if fxr < fsim[0]:
            if need >= maxfev:
                budget = 1
            else:
                need += 1
                fxe = energy[1]
                if fxe < fxr:
                    _take(sim, fsim, cand, d, last, 1, fxe)
                else:
                    _take(sim, fsim, cand, d, last, 0, fxr)
        elif fxr < fsim[last - 1]:
            _take(sim, fsim, cand, d, last, 0, fxr)
        elif fxr < fsim[last]:
            if need >= maxfev:
                budget = 1
            else:
                need += 1
                fxc = energy[2]
                if fxc <= fxr:
                    _take(sim, fsim, cand, d, last, 2, fxc)
                else:
                    state[3] = 1
        else:
            if need >= maxfev:
                budget = 1
            else:
                need += 1
                fxcc = energy[3]
                if fxcc < fsim[last]:
                    _take(sim, fsim, cand, d, last, 3, fxcc)
                else:
                    state[3] = 1
    state[0] = need
    if budget == 1:
        state[2] = 2
        cond[0] = 0
        return
    if state[3] == 1:  # a shrink next: the simplex waits for its vertices' energies
        return
    # stable insertion sort of the d + 1 vertices by energy (numpy's argsort(kind="stable"), NaN last)
    for i in range(1, d + 1):
        f = fsim[i]
        j = i
        while j > 0 and _after(fsim[j - 1], f):
            j -= 1
        if j < i:
            for q in range(d):
                x = sim[i, q]
                t = i
                while t > j:
                    sim[t, q] = sim[t - 1, q]
                    t -= 1
                sim[j, q] = x
            t = i
            while t > j:
                fsim[t] = fsim[t - 1]
                t -= 1
            fsim[j] = f
    size = wp.float64(0.0)
    for i in range(1, d + 1):
        for q in range(d):
            size = wp.max(size, wp.abs(sim[i, q] - sim[0, q]))
    if size <= xatol:
        state[2] = 1
        cond[0] = 0

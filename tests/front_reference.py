"""The DGMC front as a host loop over rings (gpps.host.dgmc.propagate_front before it moved to the device): the
test-only reference of :func:`gpps.pipeline.front.propagate_front`.

Per ring it builds the ring and picks the sources in numpy, uploads a full start array, solves
(``PixelSolver.resolve``), fetches the full outputs and merges on the host.  Kept verbatim (only the name
changed) so that tests/test_front.py and perf/front_timing.py compare the device front with it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gpps._check import as_array, as_mask
from gpps.host.dgmc import _OFFSETS, DGMCConfig, FrontResult, _check_config, select_sources
from gpps.host.merge import ranks_better


def propagate_front_host(solver, images, mask, highlight, solution: dict, *, gaussian=None, mean=None, depth=None,
                         valid=None, config: DGMCConfig | None = None, keep_better: bool = True,
                         progress=None) -> FrontResult:
    """The old host loop over rings; arguments and result as :func:`gpps.pipeline.front.propagate_front`."""
    cfg = _check_config(config)
    n_img, h, w = solver.shape
    m = as_mask("mask", mask, (h, w))
    hl = np.asarray(highlight, bool)
    if hl.shape != (h, w):
        raise ValueError(f"highlight: expected shape ({h}, {w}), got {hl.shape}")
    hl = hl & m
    for k, shp in (("normals", (h, w, 3)), ("albedo", (h, w, 3)), ("residual", (h, w)), ("flags", (h, w))):
        if k not in solution:
            raise ValueError(f"solution: expected a dict with '{k}', got keys {sorted(solution)}")
        if np.shape(solution[k]) != shp:
            raise ValueError(f"solution['{k}']: expected shape {shp}, got {np.shape(solution[k])}")
    curv = gaussian is not None and mean is not None
    if curv:
        gc = as_array("gaussian", gaussian, shape=(h, w), dtype=np.float64)
        mc = as_array("mean", mean, shape=(h, w), dtype=np.float64)
    nrm = np.array(solution["normals"], np.float32)
    alb = np.array(solution["albedo"], np.float32)
    res = np.array(solution["residual"], np.float32)
    flg = np.array(solution["flags"], np.int32)
    iters = np.zeros((h, w), np.int32)
    ring_map = np.where(hl, -1, 0).astype(np.int32)
    source = np.full((h, w, 2), -1, np.int32)
    won = np.zeros((h, w), bool)

    old = solver.config
    solver.set_config(replace(old, warm_start=True, starts=1, neighbour_radius=0, smoothness=0.0))
    try:
        start = np.where(m[..., None], nrm, 0.0)
        if images is None:
            solver.set_mask(m)
            solver.set_start(start)
        else:
            solver.upload(images, m, depth=depth, valid=valid, init_normals=start)
        solved = m & ~hl
        todo = hl.copy()
        # 8 neighbours, edge ones first (the nearer), with their offsets
        offs = sorted(_OFFSETS, key=lambda o: abs(o[0]) + abs(o[1]))
        pad = np.pad(solved, 1)
        k = 0
        while todo.any():
            pad[1:-1, 1:-1] = solved
            cand = np.stack([pad[1 + di:1 + di + h, 1 + dj:1 + dj + w] for di, dj in offs], -1)  # (H, W, 8)
            ring = todo & cand.any(-1)
            if not ring.any():
                break
            k += 1
            pi, pj = np.nonzero(ring)
            c = cand[pi, pj]  # (P, 8) solved neighbours
            # the valid candidates first (a prefix), nearest first within them
            order = np.argsort(~c, axis=1, kind="stable")
            c = np.take_along_axis(c, order, 1)
            di = np.array([o[0] for o in offs])[order]
            dj = np.array([o[1] for o in offs])[order]
            qi, qj = np.clip(pi[:, None] + di, 0, h - 1), np.clip(pj[:, None] + dj, 0, w - 1)
            if curv:
                rank, _ = select_sources(gc[pi, pj], mc[pi, pj], gc[qi, qj], mc[qi, qj], c, tolerance=cfg.tolerance,
                                         widen_factor=cfg.widen_factor, widen_steps=cfg.widen_steps)
            else:
                rank = np.zeros(pi.size, np.int64)
            rows = np.arange(pi.size)
            si, sj = qi[rows, rank], qj[rows, rank]
            init = nrm.copy()
            init[pi, pj] = nrm[si, sj]
            out = solver.resolve(ring, init)
            iters[pi, pj] = out["iterations"][pi, pj]
            take = np.ones(pi.size, bool)
            if keep_better:
                take = ranks_better(out["residual"][pi, pj], out["flags"][pi, pj], res[pi, pj])
            ti, tj = pi[take], pj[take]
            nrm[ti, tj] = out["normals"][ti, tj]
            alb[ti, tj] = out["albedo"][ti, tj]
            res[ti, tj] = out["residual"][ti, tj]
            flg[ti, tj] = out["flags"][ti, tj]
            won[ti, tj] = True
            ring_map[pi, pj] = k
            source[pi, pj, 0], source[pi, pj, 1] = si, sj
            solved |= ring
            todo &= ~ring
            if progress is not None:
                progress(k, None, f"DGMC front ring {k}: {pi.size} pixels")
    finally:
        solver.set_config(old)
    return FrontResult(normals=nrm, albedo=alb, residual=res, flags=flg, iterations=iters, ring=ring_map,
                       source=source, won=won, n_rings=k)

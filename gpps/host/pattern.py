"""A batched stencil search spread over calls: the stream's material search (ask / tell, log space).

RON's photometric material update (seed 4.1.10, Algorithm 2 step 4; :mod:`gpps.flows.ron`) minimises the
sampled fit energy ``E(x)`` over the log scene parameters ``x`` (``ks`` and the lobe width) by a grid and
then Nelder-Mead: dozens of sequential evaluations.  A stream cannot wait for that inside a frame; here every
:meth:`PatternSearch.ask` returns one *batch* of points that the caller scores in one launch (a frame's
bounded work) and hands back with :meth:`PatternSearch.tell`:

* the first batch is a ``g^d`` grid over the whole range (``g`` points per parameter);
* then each batch is the centre ``x``, the ``3^d - 1`` stencil points ``x + step * u`` (``u`` in
  ``{-1, 0, 1}^d``, clipped to the bounds) and, when the previous batch's quadratic model had a minimum, that
  minimiser (within two steps), the points RON's ``pattern`` search scores (:meth:`gpps.flows.ron.RON._pattern_search`).
  The energies of one batch come from one frame and are compared only with each other (the centre is
  re-scored in every batch: another frame's data give other energies).  The best point becomes the centre;
  the step halves when the centre stayed best (a compass search: a move keeps the step, so the search can
  travel; RON also halves after a move within the stencil, which would stop a refinement from following a
  material that drifted by more than a few steps);
* when every step is below ``tol`` (or ``budget`` batches were spent) the search is *settled*; each later
  :meth:`PatternSearch.refine` re-opens it with the step ``refine_step`` around the estimate, and it settles
  again once the centre stays best at that step (a material that drifts is followed, the step doubling after
  each move of a refinement; a steady one costs one batch per refinement).

Pure numpy; the caller owns the evaluations (:mod:`gpps.pipeline.stream_material` scores each batch with
:class:`gpps.pipeline.material.MaterialScorer`).
"""

from __future__ import annotations

import numpy as np

from gpps._check import as_array, check_number

__all__ = ["PatternSearch"]


class PatternSearch:
    """Minimise a function of ``d`` bounded parameters one batch of points at a time.

    Args:
        lo, hi: (d,) bounds of the search (e.g. log parameters).
        x0: (d,) start (the centre until the grid is told; clipped to the bounds).
        grid: points per parameter of the first batch (1: no grid, the first batch is a stencil around ``x0``).
        step0: (d,) stencil step when ``grid == 1`` (default: 1/8 of the range).
        tol: settle when every step is below this (same units as ``x``).
        refine_step: the step a :meth:`refine` re-opens the search with (default ``4 * tol``).
        budget: settle after this many stencil batches at the latest.

    Attributes:
        x: (d,) the current estimate (best point of the last batch).
        step: (d,) the current stencil step.
        settled: whether the search waits for :meth:`refine`.
        batches: batches told so far.
    """

    def __init__(self, lo, hi, x0, *, grid: int = 5, step0=None, tol: float = 0.01, refine_step: float | None = None,
                 budget: int = 40):
        self.lo = as_array("lo", lo, ndim=1, dtype=np.float64)
        self.hi = as_array("hi", hi, shape=self.lo.shape, dtype=np.float64)
        if self.lo.size < 1 or np.any(self.hi <= self.lo):
            raise ValueError(f"lo, hi: expected d >= 1 bounds with lo < hi, got {self.lo} and {self.hi}")
        d = self.lo.size
        self.grid = check_number("grid", grid, lo=1, integer=True)
        self.tol = check_number("tol", tol, lo=0.0, lo_open=True)
        self.refine_step = 4.0 * self.tol if refine_step is None else check_number("refine_step", refine_step,
                                                                                   lo=0.0, lo_open=True)
        self.budget = check_number("budget", budget, lo=1, integer=True)
        self.x = np.clip(as_array("x0", x0, shape=(d,), dtype=np.float64), self.lo, self.hi)
        self.step = (self.hi - self.lo) / 8.0 if step0 is None else as_array("step0", step0, shape=(d,), dtype=np.float64)
        if np.any(self.step <= 0):
            raise ValueError(f"step0: expected steps > 0, got {self.step}")
        u = np.stack(np.meshgrid(*([np.array([-1.0, 0.0, 1.0])] * d), indexing="ij"), -1).reshape(-1, d)
        self._stencil = u[np.any(u != 0, axis=1)]
        self._gridding = self.grid > 1
        self._step_max = (self.hi - self.lo) / max(self.grid - 1, 2) / 2.0  # the stencil step after the grid
        self._model: np.ndarray | None = None  # the last quadratic model's minimiser (scored in the next batch)
        self._asked: np.ndarray | None = None
        self.settled = False
        self.batches = 0
        self._stencils = 0
        self._refining = False

    @property
    def dims(self) -> int:
        return int(self.lo.size)

    def max_batch(self) -> int:
        """The largest batch :meth:`ask` returns: ``max(grid^d, 3^d + 1)``."""
        return max(self.grid ** self.dims if self.grid > 1 else 0, 3 ** self.dims + 1)

    def ask(self) -> np.ndarray:
        """The next batch: (K, d) points (the same batch again until it is told).  Empty (0, d) when settled."""
        if self._asked is not None:
            return self._asked
        if self.settled:
            return np.zeros((0, self.dims))
        if self._gridding:
            axes = [np.linspace(a, b, self.grid) for a, b in zip(self.lo, self.hi)]
            pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, self.dims)
        else:
            pts = [self.x] + [np.clip(self.x + u * self.step, self.lo, self.hi) for u in self._stencil]
            if self._model is not None and not np.allclose(self._model, self.x):
                pts.append(self._model)
            pts = np.asarray(pts)
        self._asked = pts
        return pts

    def tell(self, values) -> bool:
        """The energies of the last :meth:`ask` batch, in its order.  Returns whether ``x`` moved."""
        pts = self._asked
        if pts is None:
            raise ValueError("tell: expected ask() first")
        f = as_array("values", values, shape=(len(pts),), dtype=np.float64, finite=False)
        f = np.where(np.isfinite(f), f, np.inf)
        self._asked = None
        self.batches += 1
        old = self.x.copy()
        if self._gridding:
            self._gridding = False
            self.x = pts[int(np.argmin(f))].copy()
            self.step = self._step_max.copy()
            self._model = None
            return not np.array_equal(old, self.x)
        self._stencils += 1
        k = int(np.argmin(f))
        stencil = len(self._stencil) + 1
        self._model = self._quadratic(pts[:stencil], f[:stencil])
        if k != 0 and f[k] < f[0]:
            self.x = pts[k].copy()
            if self._refining:  # the optimum moved since the search settled: widen the step to follow it
                self.step = np.minimum(self.step * 2.0, self._step_max)
        else:
            self.step = self.step / 2.0
            if self._refining:  # the estimate held at the refinement step: settled again
                self._settle()
                return False
        if np.all(self.step < self.tol) or self._stencils >= self.budget:
            self._settle()
        return not np.array_equal(old, self.x)

    def refine(self) -> None:
        """Re-open a settled search around ``x`` with the step ``refine_step`` (one more batch at least)."""
        if not self.settled:
            return
        self.settled = False
        self._refining = True
        self._stencils = 0
        self._model = None
        self.step = np.full(self.dims, self.refine_step)

    def discard(self) -> None:
        """Forget the asked batch without telling it (its scores were lost, e.g. a rejected frame)."""
        self._asked = None

    def _settle(self) -> None:
        self.settled = True
        self._refining = False
        self._model = None

    def _quadratic(self, pts: np.ndarray, f: np.ndarray) -> np.ndarray | None:
        """Minimiser of the least-squares quadratic through the centre and stencil values, within two steps of
        the centre; None when the model is not convex or a value is not finite."""
        if not np.all(np.isfinite(f)):
            return None
        d = self.dims
        x, step = pts[0], self.step
        u = (pts - x) / step
        iu = np.triu_indices(d)
        a = np.hstack([np.ones((len(u), 1)), u,
                       np.stack([u[:, i] * u[:, j] * (0.5 if i == j else 1.0) for i, j in zip(*iu)], 1)])
        coef = np.linalg.lstsq(a, f, rcond=None)[0]
        g = coef[1:1 + d]
        h = np.zeros((d, d))
        h[iu] = coef[1 + d:]
        h = h + np.triu(h, 1).T
        if not np.all(np.linalg.eigvalsh(h) > 0):
            return None
        us = np.clip(-np.linalg.solve(h, g), -2.0, 2.0)
        return np.clip(x + us * step, self.lo, self.hi)

"""The stream's full mode: the material estimated from the frames, a bounded amount of device work per frame.

RON (seed 4.1.10, Algorithm 2) alternates normals with the current material, depth, and a material update
that minimises the sampled fit energy (:mod:`gpps.pipeline.material`).  :class:`gpps.pipeline.stream.Stream`
with ``StreamConfig(material="estimate")`` spreads that alternation over the frames: each frame's normals are
solved warm with the current estimate (step 1-2), its depth integrated warm (step 3), and on a *scoring* frame
one batch of candidate materials is scored on the frame (step 4, one step of the search).  This module holds
the stage of step 4, :class:`StreamMaterial`:

* ``upload()`` gathers the sample from the stream's device buffers of the current frame, so it follows a
  moving object: half the sample (``T`` tiles of a grid over the mask's bounding box) is each tile's
  brightest pixel in this frame (highlight pixels first, as RON samples them), the rest fixed random mask
  pixels.  Five launches (tile reset, score, arg-max, slots, gather) and the material-free terms, no copy.
* ``step()`` scores the candidates of the search's current batch on the sample: one launch of
  :meth:`MaterialScorer.launch`, K x P per-pixel multi-start solves.  Both are graph-capturable (the
  candidates are read from a device buffer).
* ``fetch()``, after the frame's synchronisation point, copies the (K, P) residuals back (K x P float32:
  40 KB for K = 10, P = 1024), hands their trimmed energies to the :class:`gpps.host.pattern.PatternSearch`
  and, when the search asks for more, writes the next batch to the device (a small copy, while the device
  waits for the next frame).  It returns the new estimate when it moved.

The search: a ``g^d`` grid on the first frame, then one ``3^d + 1``-candidate stencil a scoring frame until
it settles, then one stencil every ``refine_every`` frames (:mod:`gpps.host.pattern`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gpps._runtime import warp
from gpps.host.pattern import PatternSearch
from gpps.kernels import solve_batched as sb
from gpps.material import Material
from gpps.names import LOBE_PARAMETERS, LOBE_RANGES
from gpps.pipeline.material import MaterialScorer, trimmed_energy
from gpps.pipeline.solver import SolverConfig
from gpps.pipeline.stage import Stage

__all__ = ["StreamMaterial", "lobe_names", "lobe_value", "with_lobe"]


def lobe_names(brdf: str, estimate=()) -> tuple[str, ...]:
    """The parameters to estimate: ``estimate``, or all of :data:`gpps.names.LOBE_PARAMETERS` for ``brdf``
    when empty.

    Raises:
        ValueError: a model without scene parameters (Lambertian) or a name the model does not have.
    """
    allowed = LOBE_PARAMETERS[brdf]
    names = tuple(estimate) or allowed
    if not names:
        raise ValueError(f"material: the {brdf!r} model has no scene parameters to estimate; use material='known'")
    bad = [k for k in names if k not in allowed]
    if bad:
        raise ValueError(f"estimate: {brdf} has the parameters {list(allowed)}, got {bad}")
    return names


def lobe_value(material: Material, name: str) -> float:
    """A scene parameter of ``material`` (``"eta"``: Ashikhmin-Shirley's ``eta_u``)."""
    return float(material.eta_u if name == "eta" else getattr(material, name))


def with_lobe(material: Material, values: dict) -> Material:
    """``material`` with the scene parameters ``values`` (``"eta"`` sets ``eta_u = eta_v``)."""
    d = {}
    for k, v in values.items():
        if k == "eta":
            d["eta_u"] = d["eta_v"] = float(v)
        else:
            d[k] = float(v)
    # (dataclasses.replace: the checks of Material.__post_init__ without a dict round trip of every
    # field, which cost ~0.1 ms a candidate in the material search's loop)
    return replace(material, **d)


class StreamMaterial(Stage):
    """Material search of a stream: a resident sample re-gathered from each scored frame, one batch a frame.

    Args:
        solver: the stream's :class:`gpps.pipeline.solver.PixelSolver`; the sample is gathered from its
            ``images``, ``valid``, ``depth`` and ``noise`` buffers (the current converted frame).
        mask: (H, W) bool, the stream's mask.
        material: the starting guess (its model is kept; its estimated parameters are the search's start).
        names: the parameters to estimate (:func:`lobe_names`).
        samples: sample size P (at most the mask's pixels).
        candidates: most candidates per launch; the first frame's grid has ``floor(candidates^(1/d))``
            points per parameter (at most 9), each later launch ``3^d + 1``.
        starts: starts per sample pixel (RON's ``material_starts``).
        iterations: cost evaluations per start.
        trim: fraction of the largest squared residuals left out of each energy (RON's ``material_trim``).
        tol: the search settles when every log-parameter step is below this.
        refine_every: a settled search scores one stencil every this many frames.
        point: the stream's lights are point lights (the gather reads the solver's depth).
        seed: seed of the fixed random half of the sample.
        device: the solver's Warp device.
    """

    def __init__(self, solver, mask, material: Material, names, *, samples: int = 1024, candidates: int = 25,
                 starts: int = 4, iterations: int = 50, trim: float = 0.02, tol: float = 0.01,
                 refine_every: int = 8, point: bool = False, seed: int = 0, device=None):
        wp = warp()
        self.device = solver.device if device is None else device
        self.solver = solver
        self.names = tuple(names)
        self.guess = material
        self.material = material
        self.point = bool(point)
        self.refine_every = int(refine_every)
        d = len(self.names)
        if candidates < 3 ** d + 1:
            raise ValueError(f"material_candidates: expected at least 3^d + 1 = {3 ** d + 1} for {d} estimated "
                             f"parameters (one stencil a launch), got {candidates}")
        self.grid = min(int(np.floor(candidates ** (1.0 / d) + 1e-9)), 9)
        self.batch = 3 ** d + 1
        self.tol = float(tol)
        self._lo = np.log([LOBE_RANGES[k][0] for k in self.names])
        self._hi = np.log([LOBE_RANGES[k][1] for k in self.names])
        self.search = self._new_search()
        m = np.asarray(mask, bool)
        idx = np.flatnonzero(m.ravel())
        p = int(min(samples, idx.size))
        self.samples = p
        fit = SolverConfig(solver=solver.config.solver, max_iters=int(iterations), starts=int(starts),
                           neighbour_radius=0, smoothness=0.0, warm_start=False)
        _, h, w = solver.shape
        self.scorer = MaterialScorer(solver.shape, solver.camera, solver.lights, material, fit, max_samples=p,
                                     max_candidates=max(self.grid ** d, self.batch), trim=trim, device=self.device)
        # the tile grid over the mask's bounding box: T <= P/2 tiles of tile_h x tile_w pixels
        rng = np.random.default_rng(seed)
        fixed = rng.choice(idx, p, replace=False) if idx.size > p else rng.permutation(idx)
        rows, cols = np.nonzero(m)
        i0, i1, j0, j1 = int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1
        tiles = p // 2 if idx.size > p else 0  # a small mask: every pixel is in the sample, no tiles
        if tiles:
            side = int(np.ceil(np.sqrt((i1 - i0) * (j1 - j0) / tiles)))
            while int(np.ceil((i1 - i0) / side)) * int(np.ceil((j1 - j0) / side)) > tiles:
                side += 1
            self._tile = (side, side)
            self._tiles_j = int(np.ceil((j1 - j0) / side))
            tiles = int(np.ceil((i1 - i0) / side)) * self._tiles_j
        self.tiles = tiles
        self._box = wp.vec4i(i0, j0, i1, j1)
        self._score = wp.zeros((h, w), dtype=wp.float32, device=self.device) if tiles else None
        self._best = wp.zeros(max(tiles, 1), dtype=wp.float32, device=self.device)
        self._pick = wp.zeros(max(tiles, 1), dtype=wp.int32, device=self.device)
        fr, fc = (fixed // w).astype(np.int32), (fixed % w).astype(np.int32)
        self._fallback_rows = wp.array(fr[:max(tiles, 1)], dtype=wp.int32, device=self.device)
        self._fallback_cols = wp.array(fc[:max(tiles, 1)], dtype=wp.int32, device=self.device)
        pm = self.scorer.max_samples
        self.scorer.rows.assign(np.pad(fr, (0, pm - p)))  # slots [0, T) are rewritten per frame by the tiles
        self.scorer.cols.assign(np.pad(fc, (0, pm - p)))
        self.energies: np.ndarray | None = None
        self.scored = 0  # batches scored
        self._since = 0  # frames since the search settled
        self._set_batch()

    def _new_search(self) -> PatternSearch:
        x0 = np.log([lobe_value(self.guess, k) for k in self.names])
        return PatternSearch(self._lo, self._hi, x0, grid=self.grid, tol=self.tol, refine_step=4.0 * self.tol)

    def _materials(self, pts) -> list[Material]:
        return [with_lobe(self.material, dict(zip(self.names, np.exp(x)))) for x in pts]

    def _set_batch(self) -> None:
        """Write the search's next batch to the device (stencil batches padded with the centre to a fixed K, so
        that a captured launch keeps its size)."""
        pts = self.search.ask()
        if len(pts) == 0:
            return
        pts = list(pts)
        while len(pts) < self.batch:
            pts.append(pts[0])
        self._k = len(pts)
        self.scorer.set_candidates(self._materials(pts))

    @property
    def settled(self) -> bool:
        return self.search.settled

    @property
    def candidates(self) -> int:
        """K of the batch the next :meth:`step` scores."""
        return self.scorer.candidates

    def scoring(self) -> bool:
        """Whether the coming frame scores a batch: the search is open, or a settled search is due for its
        refinement (``refine_every`` frames since it settled; the refinement batch is written now).  Host only."""
        if not self.search.settled:
            return True
        self._since += 1
        if self._since >= self.refine_every:
            self._since = 0
            self.search.refine()
            self._set_batch()
            return True
        return False

    # ------------------------------------------------------------------ device work of a scoring frame

    def upload(self) -> None:
        """Gather the sample from the solver's buffers (the current frame): tile picks, then the gather and the
        material-free terms.  No copy, no host wait (graph-capturable)."""
        wp = warp()
        s, d = self.solver, self.device
        _, h, w = s.shape
        if self.tiles:
            th, tw = self._tile
            wp.launch(sb.tile_reset_kernel, dim=self.tiles, inputs=[self._best, self._pick], device=d)
            wp.launch(sb.tile_score_kernel, dim=(h, w),
                      inputs=[s.images, s.mask, self._box, self._tiles_j, th, tw], outputs=[self._score, self._best],
                      device=d)
            wp.launch(sb.tile_pick_kernel, dim=(h, w),
                      inputs=[self._score, self._box, self._tiles_j, th, tw, self._best], outputs=[self._pick],
                      device=d)
            wp.launch(sb.tile_samples_kernel, dim=self.tiles,
                      inputs=[self._pick, self._fallback_rows, self._fallback_cols, w],
                      outputs=[self.scorer.rows, self.scorer.cols], device=d)
        self.scorer.upload_device(s.images, self.scorer.rows, self.scorer.cols, self.samples, valid=s.valid,
                                  depth=s.depth if self.point else None, noise=s.noise)

    def step(self) -> None:
        """Score the current batch on the gathered sample: one launch (graph-capturable)."""
        self.scorer.launch()

    def fetch(self) -> Material | None:
        """After the frame's synchronisation: tell the search the batch's energies and write its next batch.

        Returns:
            the new estimate when the search moved it, else None.
        """
        k = self.scorer.candidates
        res = self.scorer.residual.numpy()[:k, :self.samples]
        e = trimmed_energy(res, self.scorer.trim)
        asked = self.search.ask()
        self.energies = e[:len(asked)]
        moved = self.search.tell(self.energies)
        self.scored += 1
        if self.search.settled:
            self._since = 0
        else:
            self._set_batch()
        if moved:
            self.material = with_lobe(self.material, self.estimate)
            return self.material
        return None

    def discard(self) -> None:
        """The scored frame was rejected: its energies are not told (the same batch is scored again)."""

    def reset(self) -> None:
        """Start over from the guess (the first frame was rejected: its grid scores are not trusted)."""
        self.material = self.guess
        self.search = self._new_search()
        self._since = 0
        self.scored = 0
        self.energies = None
        self._set_batch()

    @property
    def estimate(self) -> dict:
        """``{name: value}`` of the current estimate (the search's centre)."""
        return {k: float(v) for k, v in zip(self.names, np.exp(self.search.x))}

    def close(self) -> None:
        self.scorer.close()

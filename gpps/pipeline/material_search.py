"""RON's Nelder-Mead material search driven on the device: no host wait between its steps.

RON's photometric material update (:meth:`gpps.flows.ron.RON._fit_material`) minimises the trimmed sample energy
(:mod:`gpps.pipeline.material`) over the lobe parameters in log space with Nelder-Mead.  Driven from the host,
each step launches the scorer, waits for its residuals, trims them on the host and decides: on CUDA the
~30 steps of a reconstruction cost a copy and a host round trip each (256^2 x 3 images on an H100:
34 scorer fetches, 15 ms, plus the host's candidate packing and decisions), while the solves themselves take
well under a millisecond.  Here a step is five launches that read and write only device buffers
(:mod:`gpps.kernels.material_search`)::

    points (the pass's 4 candidates into the scorer's material rows: a step's, or a shrink's vertices)
    -> the scorer's recorded solve of those rows -> trimmed energies (rank, contribution, partial sums, energy)
    -> the Nelder-Mead decision, simplex update, sort and convergence test (clears the loop's condition)

and on CUDA the loop runs as one CUDA graph with a conditional while node (``wp.capture_while``, CUDA 12.4+):
the host launches it and waits once, for the result.  The first pass of a loop shape runs eagerly (the
modules load and the condition is read on the host) and is never captured; the graph is kept per shape
(warm or cold, sample size, dimension, budget and tolerance) for the life of the search, so that RON's later
rounds replay it.  Without conditional graph nodes, or on the CPU, ``wp.capture_while`` runs the same body
from the host, reading the condition after each pass.

Usage (``scorer`` a :class:`gpps.pipeline.material.MaterialScorer` holding its sample)::

    search = NelderMeadSearch(scorer, dims=2)
    search.upload(material, ("ks", "roughness"), simplex, energies, lo=lo, hi=hi, maxfev=40, xatol=1e-3)
    search.step(warm=True)
    got = search.fetch()   # {"energy", "x", "evaluations", "steps", "status", "scored"}

The trajectory equals the host method's (:meth:`gpps.flows.ron.RON._nelder_mead`): see the kernels' docstring;
tests/test_material_search.py compares them.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from gpps._check import as_array, check_choice, check_number
from gpps._runtime import resolve_device, warp
from gpps.kernels import material_search as ms
from gpps.kernels.brdf import MaterialParams
from gpps.material import Material
from gpps.names import LOBE_PARAMETERS, GraphName
from gpps.pipeline.stage import Stage

__all__ = ["NelderMeadSearch", "search_status"]

_FIELD_OF = {"ks": ms.FIELD_KS, "shininess": ms.FIELD_SHININESS, "roughness": ms.FIELD_ROUGHNESS, "eta": ms.FIELD_ETA}
_STATUS = {ms.STATUS_RUNNING: "running", ms.STATUS_CONVERGED: "converged", ms.STATUS_BUDGET: "budget"}
MAX_DIMS = 4


def search_status(code: int) -> str:
    """The name of a search status code: ``"running"``, ``"converged"`` or ``"budget"``."""
    return _STATUS[int(code)]


class NelderMeadSearch(Stage):
    """Nelder-Mead over a scorer's candidate rows, each step's decision on the device.

    Args:
        scorer: the candidates' scorer: a :class:`gpps.pipeline.material.MaterialScorer` (or an object with its
            ``device``, ``max_candidates``, ``max_samples``, ``trim``, ``samples``, ``brdf``, the device buffers
            ``mats`` (K_max,) MaterialParams and ``residual`` (K_max, P_max) float32, and
            ``launch(count=K, warm=...)`` that scores the first K rows of ``mats`` into ``residual`` without a
            host wait).  It must hold its sample (an upload) when :meth:`step` runs.
        dims: d, the number of searched parameters (1 to 4); a pass scores 4 candidates, so the scorer needs
            ``max_candidates >= 4``.
        graph: ``"auto"``: the loop as a CUDA graph with a conditional node where the device supports one
            (CUDA 12.4+ driver and toolkit), else from the host; ``"off"``: always from the host.

    Buffers (allocated once): the simplex ``sim`` (d + 1, d) and ``fsim`` (d + 1,) float64, the step's candidates
    ``cand`` (4, d) and their ``energy``, the trimmed-energy scratch ``before`` (rank counts), ``contrib``
    (4, P_max) and ``partial``,
    the bounds, the material base row, ``state`` [evaluations read, passes, status, phase] and the loop condition
    (``sim``, ``fsim`` and the bounds are views of one float64 buffer; ``fields``, ``state`` and ``cond`` of one
    int32 buffer).
    """

    @staticmethod
    def kernel_modules() -> list:
        """The Warp modules this stage launches (:meth:`gpps.flows.ron.RON.kernel_plan`)."""
        return [warp().get_module(ms.__name__)]

    def __init__(self, scorer, dims: int, *, graph: GraphName = "auto"):
        wp = warp()
        self.dims = check_number("dims", dims, lo=1, hi=MAX_DIMS, integer=True)
        self.graph = check_choice("graph", graph, GraphName)
        kc = ms.SEARCH_POINTS
        for name in ("mats", "residual", "launch", "max_candidates", "max_samples", "trim", "device"):
            if not hasattr(scorer, name):
                raise TypeError(f"scorer: expected a MaterialScorer (or an object with {name!r}), "
                                f"got {type(scorer).__name__}")
        if int(scorer.max_candidates) < kc:
            raise ValueError(f"scorer: expected max_candidates >= {kc}, got {scorer.max_candidates}")
        self.scorer = scorer
        self.device = resolve_device(scorer.device)
        self._settle(*self.kernel_modules())
        self.points = kc
        d, dev = self.dims, self.device
        # the small per-search arrays live in one float64 and one int32 buffer (views): an upload is two copies and
        # the struct row, a fetch two copies (each copy costs ~0.1 ms of host time on CUDA, four searches a call)
        self._f64 = self._buffer((d + 1) * d + (d + 1) + 2 * d + 1, wp.float64, dev)
        self._i32 = self._buffer(d + ms.STATE_SIZE + 1, wp.int32, dev)
        self.sim = self._f64[0:(d + 1) * d].reshape((d + 1, d))
        self.fsim = self._f64[(d + 1) * d:(d + 1) * (d + 1)]
        self.lo = self._f64[(d + 1) * (d + 1):(d + 1) * (d + 1) + d]
        self.hi = self._f64[(d + 1) * (d + 1) + d:(d + 1) * (d + 1) + 2 * d]
        self.f0 = self._f64[(d + 1) * (d + 1) + 2 * d:]  # the start's energy, when the search scores its simplex
        self.fields = self._i32[0:d]
        self.state = self._i32[d:d + ms.STATE_SIZE]
        self.cond = self._i32[d + ms.STATE_SIZE:]
        self.cand = self._buffer((kc, d), wp.float64, dev)
        self.energy = self._buffer(kc, wp.float64, dev)
        self.contrib = self._buffer((kc, int(scorer.max_samples)), wp.float64, dev)
        self.before = self._buffer((kc, int(scorer.max_samples)), wp.int32, dev)  # rank counts (zero between passes)
        self.partial = self._buffer((kc, ms.PARTIAL_LANES), wp.float64, dev)
        self.base = self._buffer(1, MaterialParams, dev)
        self._graphs: dict = {}
        self._host: dict | None = None  # the uploaded search's host-side result when it needs no step
        self._init = False  # the uploaded search scores its simplex itself (its first pass)
        self._spec = None
        self._closed = False

    # ------------------------------------------------------------------ upload

    @property
    def scores_simplex(self) -> bool:
        """Whether :meth:`upload` takes a simplex without energies here (its d + 1 vertices fit one pass)."""
        return self.dims + 1 <= self.points

    def upload(self, material: Material, names: Sequence[str], simplex, energies, *, lo, hi, maxfev: int,
               xatol: float, evaluations: int | None = None) -> None:
        """Start a search from a simplex, scored or not.

        Args:
            material: the base material (its model is the scorer's); the searched lobe parameters ``names``
                are set from each point, the rest kept.
            names: the d searched parameters (:data:`gpps.names.LOBE_PARAMETERS` of the model).
            simplex: (d + 1, d) vertices in log-parameter space (vertex 0 the start).
            energies: (d + 1,) their energies (float64), or None (:attr:`scores_simplex`): the search's first pass
                scores the vertices on the device (clipped to the bounds, as the host's scoring clips them; the
                kernels' init pass), and :meth:`fetch` returns vertex 0's energy as ``f_start``.
            lo, hi: (d,) log bounds: every point the search makes is clipped to them and kept clipped (scipy's
                bounded Nelder-Mead; the simplex should lie inside: :func:`gpps.flows.ron.initial_simplex`).
            maxfev: the most evaluations the method reads, the initial simplex's included (> d + 1).
            xatol: the simplex size at convergence (log units).
            evaluations: evaluations already read (None: d + 1, the simplex).

        The simplex is sorted (stable) here; when it has already converged :meth:`step` does nothing.
        """
        self._check_open()
        d = self.dims
        if not isinstance(material, Material):
            raise TypeError(f"material: expected gpps.Material, got {type(material).__name__}")
        if material.brdf != self.scorer.brdf:
            raise ValueError(f"material: expected a {self.scorer.brdf!r} material (the scorer's model), "
                             f"got {material.brdf!r}")
        names = tuple(names)
        if len(names) != d or any(n not in LOBE_PARAMETERS[material.brdf] for n in names):
            raise ValueError(f"names: expected {d} parameters of {material.brdf!r} from "
                             f"{LOBE_PARAMETERS[material.brdf]}, got {names}")
        sim = as_array("simplex", simplex, shape=(d + 1, d), dtype=np.float64)
        init = energies is None
        if init and not self.scores_simplex:
            raise ValueError(f"energies: expected the simplex's {d + 1} energies ({d + 1} vertices do not fit a "
                             f"pass of {self.points}), got None")
        f = (np.zeros(d + 1) if init
             else as_array("energies", energies, shape=(d + 1,), dtype=np.float64, finite=False))
        lo = as_array("lo", lo, shape=(d,), dtype=np.float64)
        hi = as_array("hi", hi, shape=(d,), dtype=np.float64)
        if np.any(np.isnan(f)):
            raise ValueError("energies: expected numbers (inf allowed), got NaN")
        if np.any(lo > hi):
            raise ValueError("lo, hi: expected lo <= hi")
        need = d + 1 if evaluations is None else check_number("evaluations", evaluations, lo=0, integer=True)
        maxfev = check_number("maxfev", maxfev, lo=need + 1, integer=True)
        xatol = check_number("xatol", xatol, lo=0.0)
        converged = False
        if not init:  # (scored: sorted and tested here; else by the init pass)
            order = np.argsort(f, kind="stable")
            sim, f = sim[order], f[order]
            converged = bool(np.max(np.abs(sim[1:] - sim[0])) <= xatol)
        self._host = {"energy": float(f[0]), "x": sim[0].copy(), "evaluations": int(need), "steps": 0,
                      "status": "converged", "scored": 0, "f_start": None} if converged else None
        self._init = init
        self._spec = (names, int(maxfev), float(xatol))
        self._f64.assign(np.concatenate([sim.ravel(), f, lo, hi, [np.nan]]))  # (sim, fsim, lo, hi, f0)
        phase = ms.PHASE_INIT if init else ms.PHASE_STEP
        self._i32.assign(np.array([_FIELD_OF[n] for n in names] + [need, 0, ms.STATUS_RUNNING, phase]
                                  + [0 if converged else 1], np.int32))  # (fields, state, cond)
        row = np.zeros(1, dtype=MaterialParams.numpy_dtype())
        m = material
        row[0] = (m.device_tag, m.ks, m.shininess, m.roughness, m.f0, m.eta_u, m.eta_v)
        self.base.assign(row)

    # ------------------------------------------------------------------ step

    def _pass(self, warm: bool, p: int, keep: int, maxfev: int, xatol: float) -> None:
        """One search pass (a step, or a shrink's vertices): seven launches (no host wait, graph-capturable)."""
        wp = warp()
        d, kc, dev = self.dims, self.points, self.device
        wp.launch(ms.search_points_kernel, dim=kc,
                  inputs=[self.sim, d, self.lo, self.hi, self.fields, self.base, self.state],
                  outputs=[self.cand, self.scorer.mats], device=dev)
        self.scorer.launch(count=kc, warm=warm)
        res = self.scorer.residual
        seg = ms.RANK_SEGMENT
        wp.launch(ms.trimmed_rank_kernel, dim=(kc, p, (p + seg - 1) // seg), inputs=[res, p, seg],
                  outputs=[self.before], device=dev)
        wp.launch(ms.trimmed_contrib_kernel, dim=(kc, p), inputs=[res, keep], outputs=[self.before, self.contrib],
                  device=dev)
        wp.launch(ms.trimmed_partial_kernel, dim=(kc, ms.PARTIAL_LANES), inputs=[self.contrib, p],
                  outputs=[self.partial], device=dev)
        wp.launch(ms.trimmed_energy_kernel, dim=kc, inputs=[self.partial, keep], outputs=[self.energy], device=dev)
        wp.launch(ms.search_step_kernel, dim=1,
                  inputs=[self.energy, self.cand, d, maxfev, wp.float64(xatol)],
                  outputs=[self.sim, self.fsim, self.f0, self.state, self.cond], device=dev)

    def uses_graph(self) -> bool:
        """Whether :meth:`step` runs the loop as a CUDA graph with a conditional node here."""
        wp = warp()
        return (self.graph == "auto" and self.device.startswith("cuda")
                and bool(wp.is_conditional_graph_supported()))

    def step(self, *, warm: bool = False) -> None:
        """Run the search to convergence or its budget: on CUDA one graph launch (see the module docstring).

        Args:
            warm: score from the scorer's warm start (``MaterialScorer.set_start``), one start per pixel.
        """
        self._check_open()
        if self._spec is None:
            raise ValueError("step: expected upload() first")
        if self._host is not None:
            return
        p = int(getattr(self.scorer, "samples", 0))
        if p <= 0:
            raise ValueError("step: expected the scorer to hold its sample (an upload) first")
        if p > self.contrib.shape[1]:
            raise ValueError(f"scorer: expected at most {self.contrib.shape[1]} samples, got {p}")
        keep = max(1, int(round(p * (1.0 - float(self.scorer.trim)))))
        _, maxfev, xatol = self._spec
        wp = warp()
        args = (bool(warm), p, keep, maxfev, xatol)
        if not self.uses_graph():
            wp.capture_while(self.cond, self._pass, warm=args[0], p=p, keep=keep, maxfev=maxfev, xatol=xatol)
            return
        g = self._graphs.get(args)
        if g is None:
            # the first pass of this shape eagerly (modules load, nothing is captured cold), then the rest as a graph
            self._pass(*args)
            if int(self.cond.numpy()[0]) == 0:
                return
            wp.capture_begin(device=self.device)
            try:
                wp.capture_while(self.cond, self._pass, warm=args[0], p=p, keep=keep, maxfev=maxfev, xatol=xatol)
            finally:
                g = wp.capture_end(device=self.device)
            self._graphs[args] = g
        wp.capture_launch(g)

    # ------------------------------------------------------------------ fetch

    def fetch(self) -> dict:
        """The search's result (one small copy): ``energy`` (float), ``x`` (d,) the best vertex (log space,
        inside the bounds, as the host method returns it), ``evaluations`` read, ``steps`` (passes: steps and shrinks,
        and the init pass), ``status`` (``"converged"`` or ``"budget"``), ``scored`` (candidates solved: 4 a pass,
        the init pass's d + 1 vertices) and ``f_start``: vertex 0's energy when the search scored its simplex
        (``upload(energies=None)``), else None."""
        self._check_open()
        if self._spec is None:
            raise ValueError("fetch: expected upload() first")
        if self._host is not None:
            return dict(self._host, x=self._host["x"].copy())
        d = self.dims
        f64, state = self._f64.numpy(), self._i32.numpy()[d:d + ms.STATE_SIZE]  # (two copies)
        sim, fsim = f64[:(d + 1) * d].reshape(d + 1, d), f64[(d + 1) * d:(d + 1) * (d + 1)]
        passes = int(state[1])
        scored = passes * self.points - ((self.points - (d + 1)) if self._init and passes else 0)
        return {"energy": float(fsim[0]), "x": sim[0].copy(), "evaluations": int(state[0]), "steps": passes,
                "status": search_status(state[2]), "scored": scored,
                "f_start": float(f64[-1]) if self._init else None}

    def run(self, *args, warm: bool = False, **kwargs) -> dict:
        """``upload(*args, **kwargs)``, ``step(warm=warm)`` and ``fetch()``."""
        self.upload(*args, **kwargs)
        self.step(warm=warm)
        return self.fetch()

    def close(self) -> None:
        """Give the buffers back to the pool and drop the graphs; the search refuses work afterwards."""
        self._graphs.clear()
        self._release_buffers()
        for name in ("_f64", "_i32", "sim", "fsim", "cand", "energy", "contrib", "before", "partial", "lo", "hi",
                     "fields", "base", "state", "cond", "scorer"):
            self.__dict__.pop(name, None)
        self._closed = True

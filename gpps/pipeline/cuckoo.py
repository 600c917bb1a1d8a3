"""The cuckoo search stage (seed 6.1-6.9, Algorithm 6): buffers and launches.

:class:`CuckooSearch` runs ``P`` independent searches of ``K`` nests each (one
per pixel in the photometric refinement) for any objective of
:mod:`gpps.kernels.cuckoo` form.  Example (a test's analytic objective)::

    search = CuckooSearch(P, objective=sphere_objective, data_type=SphereData, config=CuckooConfig(seed=1))
    search.init(nests0)                   # (P, K, 5) starting habitats
    search.run(data, generations=500)     # progress(done, total, message) optional
    x, f = search.best()                  # (P, 5), (P,)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from gpps._check import check_number
from gpps._runtime import resolve_device, warp

__all__ = ["CuckooConfig", "CuckooSearch", "mantegna_sigma_u"]

EggTarget = Literal["own", "random"]


def mantegna_sigma_u(lam: float) -> float:
    """``sigma_u`` of Mantegna's algorithm (6.7) for the Levy exponent ``lam`` (with sigma_v = 1, 6.9)."""
    lam = float(lam)
    num = math.gamma(1.0 + lam) * math.sin(math.pi * lam / 2.0)
    den = math.gamma((1.0 + lam) / 2.0) * lam * 2.0 ** ((lam - 1.0) / 2.0)
    return (num / den) ** (1.0 / lam)


@dataclass(frozen=True)
class CuckooConfig:
    """Cuckoo search settings.

    Attributes:
        nests: habitats per search (K >= 2).
        generations: generations per :meth:`CuckooSearch.run` (>= 0).
        beta: step size of the Levy flight (6.1); the seed's 6.2.5 uses 0.01.
        p_c: probability that a host finds an egg (abandonment fraction, in [0, 1]);
            the seed's 6.2.5 uses 0.4.
        levy_exponent: Mantegna's exponent lambda in (0, 2] (6.5, 6.7); 1.5 as in
            Yang & Deb.  (The seed writes beta for both the step size and this
            exponent; with an exponent of 0.01 the steps would be almost all
            zero or astronomically large, so they are two settings here.)
        seed: random seed: the same seed gives the same result on every device.
        egg_target: which nest an egg competes with: ``"own"`` (the nest that laid it, as in
            Yang & Deb's reference code) or ``"random"`` (Algorithm 6's literal "choose a habitat
            j randomly", which collapses the population early; see :mod:`gpps.kernels.cuckoo`).
    """

    nests: int = 16
    generations: int = 200
    beta: float = 0.01
    p_c: float = 0.4
    levy_exponent: float = 1.5
    seed: int = 0
    egg_target: EggTarget = "own"

    def __post_init__(self):
        if self.egg_target not in get_args(EggTarget):
            raise ValueError(f"egg_target: expected one of {list(get_args(EggTarget))}, got {self.egg_target!r}")
        if not isinstance(self.nests, (int, np.integer)) or isinstance(self.nests, bool) or self.nests < 2:
            raise ValueError(f"nests: expected an integer >= 2, got {self.nests!r}")
        if not isinstance(self.generations, (int, np.integer)) or isinstance(self.generations, bool) or self.generations < 0:
            raise ValueError(f"generations: expected an integer >= 0, got {self.generations!r}")
        object.__setattr__(self, "beta", check_number("beta", self.beta, lo=0.0, lo_open=True))
        object.__setattr__(self, "p_c", check_number("p_c", self.p_c, lo=0.0, hi=1.0))
        object.__setattr__(self, "levy_exponent", check_number("levy_exponent", self.levy_exponent, lo=0.0, hi=2.0, lo_open=True))
        if not isinstance(self.seed, (int, np.integer)) or isinstance(self.seed, bool) or not 0 <= self.seed < 2**31:
            raise ValueError(f"seed: expected an integer in [0, 2^31), got {self.seed!r}")


class CuckooSearch:
    """``n_search`` independent cuckoo searches over 5-vectors, on one Warp device.

    Args:
        n_search: number of searches P (>= 1).
        objective: a ``@wp.func (x: vec5, p: int, data) -> float`` to minimise.
        data_type: the ``@wp.struct`` type of its ``data``.
        config: :class:`CuckooConfig`.
        lo, hi: (5,) bounds of the habitats (default +-1e30).
        device: Warp device.
    """

    def __init__(self, n_search: int, *, objective, data_type, config: CuckooConfig | None = None,
                 lo=None, hi=None, device=None):
        wp = warp()
        from gpps.kernels import cuckoo as ck

        self._ck = ck
        self.config = config or CuckooConfig()
        if not isinstance(self.config, CuckooConfig):
            raise TypeError(f"config: expected CuckooConfig, got {type(self.config).__name__}")
        n_search = int(n_search)
        if n_search < 1:
            raise ValueError(f"n_search: expected >= 1, got {n_search}")
        self.device = resolve_device(device)
        self.n_search = n_search
        self._eval, self._gen = ck.make_search_kernels(objective, data_type)
        k = self.config.nests
        d = self.device
        self.nests = wp.zeros((n_search, k), dtype=ck.vec5, device=d)
        self.fit = wp.zeros((n_search, k), dtype=wp.float32, device=d)
        self.best_index = wp.zeros(n_search, dtype=wp.int32, device=d)
        self.lo = ck.vec5(*(np.full(5, -1e30) if lo is None else np.asarray(lo, np.float64).reshape(5)))
        self.hi = ck.vec5(*(np.full(5, 1e30) if hi is None else np.asarray(hi, np.float64).reshape(5)))
        self.sigma_u = mantegna_sigma_u(self.config.levy_exponent)
        self.generation = 0

    def init(self, nests) -> None:
        """Set the starting habitats: (P, K, 5) numpy (clipped to the bounds) or a Warp array."""
        shape = (self.n_search, self.config.nests, 5)
        a = np.asarray(nests, dtype=np.float32)
        if a.shape != shape:
            raise ValueError(f"nests: expected shape {shape}, got {a.shape}")
        lo = np.array(self.lo, np.float32)
        hi = np.array(self.hi, np.float32)
        self.nests.assign(np.clip(a, lo, hi))
        self.generation = 0

    def evaluate(self, data) -> None:
        """Objective values of all nests and the best of each search (after :meth:`init` or a data change)."""
        warp().launch(self._eval, dim=self.n_search, inputs=[self.nests, data], outputs=[self.fit, self.best_index],
                      device=self.device)

    def run(self, data, generations: int | None = None, *, progress=None) -> None:
        """Evaluate, then run ``generations`` generations (default ``config.generations``).

        The random stream of generation g is ``rand_init(seed, g * P + p)``, g counted from the last
        :meth:`init`, so runs continue the same sequence and are reproducible.
        """
        wp = warp()
        g_total = self.config.generations if generations is None else int(generations)
        if g_total < 0:
            raise ValueError(f"generations: expected >= 0, got {g_total}")
        self.evaluate(data)
        c = self.config
        for g in range(g_total):
            wp.launch(
                self._gen, dim=self.n_search,
                inputs=[self.nests, self.fit, self.best_index, data, int(c.seed), int(self.generation),
                        float(c.beta), float(c.p_c), float(self.sigma_u), float(c.levy_exponent), self.lo, self.hi,
                        int(c.egg_target == "random")],
                device=self.device,
            )
            self.generation += 1
            if progress is not None and (g % 10 == 9 or g == g_total - 1):
                progress(g + 1, g_total, "cuckoo search")

    def best(self) -> tuple[np.ndarray, np.ndarray]:
        """The best habitat (P, 5) and its objective value (P,) of every search."""
        nests = self.nests.numpy()
        fit = self.fit.numpy()
        b = self.best_index.numpy()
        idx = np.arange(self.n_search)
        return nests[idx, b], fit[idx, b]

"""Whether another reflectance model fits the material sample better than the sampling noise of the sample allows.

RON's first material fit can compare reflectance models (``RONConfig.models``): each model's lobe parameters are
fitted on the same sample pixels, and its energy is the trimmed mean of the pixels' squared residuals at its best
parameters (:func:`gpps.pipeline.material.trimmed_energy`).  Taking whichever energy is lower treats a difference of
0.1 % as a verdict, yet the sample is a few hundred to a few thousand pixels drawn from the object, and a
difference that small can be the draw's.  Where both models are wrong and the per-pixel normals absorb the
difference, the lower energy then says nothing about the normals (on DiLiGenT's bear the plastic model's sampled
energy is 0.1 % below Blinn-Phong's, and its normals are 1.1 deg worse on average, flattened by 3-4 deg where the
surface turns away from the camera; perf/results/s33/README.md).

So the configured model is the null hypothesis and another model replaces it only on evidence: over the sample
pixels both energies keep (each leaves out its own largest ``trim`` share), the per-pixel differences of the
squared residuals must have a mean above zero by more than :data:`gpps.names.MODEL_SWITCH_Z` standard errors (a
one-sided paired test at the conventional 1 % level; the pixels are the sample's independent draws), and the other
model's trimmed energy must be the lower.  This is a significance level, not a tuned margin: where a model is right
(a metal under the conductor, a smooth dielectric coating under the plastic model) its energy falls by tens of per
cent, far outside the sample's spread.
"""

from __future__ import annotations

import numpy as np

from gpps import names

__all__ = ["energy_drop_evidence"]


def _kept(r2: np.ndarray, keep: int) -> np.ndarray:
    """(P,) bool: the ``keep`` smallest values of ``r2`` (P,) (a partition: ties at the edge broken by position)."""
    out = np.zeros(r2.size, bool)
    out[np.argpartition(r2, keep - 1)[:keep] if keep < r2.size else slice(None)] = True
    return out


def energy_drop_evidence(base_residual, other_residual, trim: float, *, z: float | None = None) -> dict:
    """Whether ``other``'s trimmed energy is lower than ``base``'s beyond the sample's noise (module docstring).

    Args:
        base_residual: (P,) RMS residual of each sample pixel under the configured model at its best parameters
            (image units).
        other_residual: (P,) the same pixels under the other model at its best parameters.
        trim: the energy's trimmed fraction (``RONConfig.material_trim``), in [0, 0.5].
        z: the one-sided test's critical value (None: :data:`gpps.names.MODEL_SWITCH_Z`).

    Returns:
        dict: ``energy_base``, ``energy_other`` (the trimmed energies of the whole sample, image units squared, as
        :func:`gpps.pipeline.material.trimmed_energy`), ``drop`` (``1 - other / base``), ``pixels`` (both keep),
        ``z`` (the paired differences' mean over its standard error there), ``z_critical`` and ``significant``.

    Raises:
        ValueError: the two residual arrays differ in shape, are not 1-D, or hold a non-finite value.
    """
    a = np.asarray(base_residual, np.float64)
    b = np.asarray(other_residual, np.float64)
    if a.ndim != 1 or a.shape != b.shape:
        raise ValueError(f"other_residual: expected the shape of base_residual, (P,), got {b.shape} and {a.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("base_residual / other_residual: expected finite residuals")
    crit = names.MODEL_SWITCH_Z if z is None else float(z)
    out = {"energy_base": 0.0, "energy_other": 0.0, "drop": 0.0, "pixels": 0, "z": 0.0, "z_critical": crit,
           "significant": False}
    if a.size == 0:
        return out
    keep = max(1, int(round(a.size * (1.0 - float(trim)))))
    a2, b2 = a * a, b * b
    ka, kb = _kept(a2, keep), _kept(b2, keep)
    e_a, e_b = float(a2[ka].mean()), float(b2[kb].mean())
    d = (a2 - b2)[ka & kb]
    out.update(energy_base=e_a, energy_other=e_b, drop=(1.0 - e_b / e_a) if e_a > 0 else 0.0, pixels=int(d.size))
    if d.size < 2:
        return out
    mean, sd = float(d.mean()), float(d.std(ddof=1))
    stat = mean / (sd / np.sqrt(d.size)) if sd > 0 else (np.inf if mean > 0 else 0.0)
    out.update(z=float(stat), significant=bool(stat > crit and e_b < e_a))
    return out

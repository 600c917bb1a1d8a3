"""The rule that merges two solves of the same pixels: keep the lower residual, where it can rank."""

from __future__ import annotations

import numpy as np

from gpps.names import FLAG_FEW_OBSERVATIONS

__all__ = ["ranks_better"]


def ranks_better(new_residual, new_flags, old_residual):
    """Where another start's solution beats the current one: a lower residual, on a pixel
    with 3 lit observations (an under-determined pixel fits a family of normals, so its
    residual cannot rank starts).  Element-wise over matching arrays; returns bool."""
    return (np.asarray(new_residual) < np.asarray(old_residual)) & ((np.asarray(new_flags) & FLAG_FEW_OBSERVATIONS) == 0)

"""The one protocol of every stage: ``upload`` / ``step`` / ``fetch`` / ``close`` (and ``run``, the three in one).

A stage allocates its device buffers once, for one problem size, in ``__init__``; after that:

* ``upload(...)``: copy the inputs into the stage's buffers, checking their shapes against the size the
  stage was built for ("expected ..., got ...");
* ``step(...)``: launch the work on the stage's device; nothing is copied back and the host does not wait
  (a step can be captured in a CUDA graph where the stage says so);
* ``fetch(...)``: copy the results the caller asks for to the host (numpy) and return them;
* ``close()``: release the device buffers (also on leaving a ``with`` block); a closed stage refuses work;
* ``run(...)``: ``upload(...)``, ``step()``, ``fetch()`` in one call, for callers that do not keep data on
  the device between calls.

Stages hold no numpy algorithms (those live in :mod:`gpps.host`) and no whole flows (:mod:`gpps.flows`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from gpps.pipeline import buffers
from gpps.pipeline.prefetch import settle

__all__ = ["Stage"]


class Stage(ABC):
    """Base class of the stages: the protocol above, with ``run`` and the context manager written once.
    A stage that lacks one of the three verbs cannot be instantiated (``abc``)."""

    @abstractmethod
    def upload(self, *args, **kwargs) -> None:
        """Copy the inputs into the stage's buffers (shapes checked)."""

    @abstractmethod
    def step(self, *args, **kwargs) -> None:
        """Launch the work on the stage's device."""

    @abstractmethod
    def fetch(self, *args, **kwargs):
        """Copy the results to the host and return them."""

    def close(self) -> None:
        """Release the device buffers: those taken with :meth:`_buffer` go back to the process's pool
        (:mod:`gpps.pipeline.buffers`).  A subclass that overrides it calls :meth:`_release_buffers`."""
        self._release_buffers()

    def _buffer(self, shape, dtype, device, fill=0):
        """A device buffer from the process's pool (zeroed, or filled with ``fill``), given back at :meth:`close`."""
        a = buffers.take(shape, dtype, device, fill)
        self.__dict__.setdefault("_pooled", []).append(a)
        return a

    def _settle(self, *kernels) -> None:
        """Before this stage's first launches: wait for a helper's compile of these kernels' (or modules') Warp
        modules if one is running, so the launch loads the helper's binary instead of building it a second time
        (:func:`gpps.pipeline.prefetch.settle`; a no-op without a helper).  Needs ``self.device``."""
        for k in kernels:
            settle(k, self.device)

    def _check_open(self) -> None:
        """ValueError naming the stage once :meth:`close` set ``_closed``: its buffers may belong to another
        stage by then (the pool hands them out again)."""
        if self.__dict__.get("_closed", False):
            raise ValueError(f"{type(self).__name__}: closed (its device buffers were released)")

    def _release_buffers(self) -> None:
        """Give the buffers of :meth:`_buffer` back to the pool (once)."""
        buffers.give(self.__dict__.pop("_pooled", []))

    def run(self, *args, **kwargs):
        """``upload(*args, **kwargs)``, ``step()`` and ``fetch()``: the stage's one-shot form."""
        self.upload(*args, **kwargs)
        self.step()
        return self.fetch()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

"""The process's pool of stage buffers (gpps.pipeline.buffers): reuse, fill, cap, and whole reconstructions
that take their buffers from it give the results of fresh ones."""

from __future__ import annotations

import numpy as np
import pytest
from cases import make_case

import gpps
from gpps._runtime import warp
from gpps.pipeline import buffers
from gpps.pipeline.solver import PixelSolver


def test_take_give_reuses_and_refills(device):
    wp = warp()
    buffers.clear()
    a = buffers.take((5, 7), wp.float32, device)
    a.fill_(3.0)
    buffers.give([a])
    b = buffers.take((5, 7), wp.float32, device)
    assert b is a and np.all(b.numpy() == 0.0)  # the same buffer, zeroed as a new one
    b.fill_(2.0)
    buffers.give([b])
    c = buffers.take((5, 7), wp.float32, device, fill=1)
    assert c is a and np.all(c.numpy() == 1.0)
    d = buffers.take((5, 7), wp.float32, device)  # none free: a new one
    assert d is not c and np.all(d.numpy() == 0.0)
    e = buffers.take(7, wp.int32, device)  # another key
    assert e.shape == (7,) and e.dtype == wp.int32
    buffers.clear()


def test_free_buffers_capped_per_key(device):
    wp = warp()
    buffers.clear()
    arrs = [buffers.take(4, wp.uint8, device) for _ in range(buffers.MAX_PER_KEY + 2)]
    before = buffers.stats()
    buffers.give(arrs)
    buffers.give(arrs[:1])  # a buffer given twice is kept once
    after = buffers.stats()
    assert after["free"] - before["free"] == buffers.MAX_PER_KEY
    assert after["dropped"] - before["dropped"] == 3
    buffers.clear()
    assert buffers.stats()["free"] == 0


def test_closed_solver_refuses_work(device):
    img, lights, sc, mat = make_case("sphere", 24, "orthographic", "directional", "lambertian", device=device)
    s = PixelSolver(img.shape[:3], sc.camera, lights, mat, device=device)
    s.run(img, sc.mask)
    s.close()
    with pytest.raises(ValueError, match="closed"):
        s.upload(img, sc.mask)
    with pytest.raises(ValueError, match="closed"):
        s.fetch()


def test_reconstructions_from_pooled_buffers_equal_fresh_ones(device):
    """Two reconstructions of one size in a row: the second takes the first's buffers (zeroed / refilled)
    and gives the same result as the first (and as one with an empty pool)."""
    img, lights, sc, _ = make_case("bumps", 32, "perspective", "directional", "cook-torrance", device=device)
    buffers.clear()
    run = lambda: gpps.reconstruct(img, sc.mask, lights, camera=sc.camera, material="cook-torrance", device=device)
    r0 = run()
    s0 = buffers.stats()
    r1 = run()
    s1 = buffers.stats()
    assert s1["reused"] - s0["reused"] >= 20  # the solvers', the scorer's and DGMC's buffers came back
    buffers.clear()
    r2 = run()
    for r in (r1, r2):
        assert np.array_equal(r.normals, r0.normals)
        assert np.array_equal(r.albedo, r0.albedo)
        assert r.estimated == r0.estimated

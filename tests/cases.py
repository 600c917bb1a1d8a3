"""Evaluation cases shared by the tests and the perf scripts: rendered scenes solved with known lights."""

from __future__ import annotations

import time
from contextlib import contextmanager

import numpy as np

from gpps.host.metrics import depth_error  # noqa: F401  (re-exported for the tests and perf scripts)
from gpps.names import BRDF_NAMES

BRDFS = list(BRDF_NAMES)
# lights a model's per-pixel fit needs before its normals are determined: 3 for every model with a diffuse term; the
# conductor (no diffuse term: a normal and a colour seen only through the lobe, which most lights miss) needs 6
# (tests/test_conductor.py: exact with 6 and 12 lights, 6-10 deg off with 3)
MIN_LIGHTS = {b: 3 for b in BRDF_NAMES} | {"conductor": 6}


def make_case(scene_name, size, camera, light_kind, brdf, noise=0.0, device=None, n_lights=3):
    """(images divided by intensities, unit-intensity lights, scene, material)."""
    from gpps.lights import DirectionalLights, PointLights
    from gpps.material import Material
    from gpps.host.scenes import make_scene
    from gpps.flows.synthetic import default_lights, render

    sc = make_scene(scene_name, size, camera)
    mat = Material.default_for(brdf)
    L = default_lights(light_kind, n_lights)
    img = render(sc, mat, L, bits=16, noise=noise, device=device)
    img = img / np.asarray(L.intensities, np.float32)[:, None, None, :]
    Lu = DirectionalLights(L.directions) if light_kind == "directional" else PointLights(L.positions)
    return img, Lu, sc, mat


def run_case(scene_name, size, camera, light_kind, brdf, *, noise=0.0, solver="lm", device=None, n_lights=3, **options):
    """Solve one rendered case with least squares and ``solver`` (``options``: further SolverConfig fields); errors and time."""
    from gpps.host.metrics import normal_errors
    from gpps.flows.photometric import solve_normals

    img, L, sc, mat = make_case(scene_name, size, camera, light_kind, brdf, noise, device, n_lights)
    depth = sc.depth if light_kind == "point" else None
    ls = solve_normals(img, sc.mask, L, camera=sc.camera, material=mat, solver="none", depth=depth, device=device)
    t = time.perf_counter()
    nl = solve_normals(img, sc.mask, L, camera=sc.camera, material=mat, solver=solver, depth=depth, device=device, **options)
    dt = time.perf_counter() - t
    e_ls = normal_errors(ls.normals, sc.normals, sc.mask)
    e_nl = normal_errors(nl.normals, sc.normals, sc.mask)
    return {
        "scene": scene_name,
        "size": size,
        "camera": camera,
        "lights": light_kind,
        "n_lights": n_lights,
        "brdf": brdf,
        "noise": noise,
        "solver": solver,
        "maen_least_squares": e_ls["mean"],
        "maen": e_nl["mean"],
        "median": e_nl["median"],
        "under_5deg": e_nl["under_5deg"],
        "slant_mae": e_nl["slant_mae"],
        "tilt_mae": e_nl["tilt_mae"],
        "maen_determined": normal_errors(nl.normals, sc.normals, sc.mask & ((nl.flags & 2) == 0))["mean"],
        "underdetermined_fraction": float(((nl.flags & 2) != 0)[sc.mask].mean()),
        "options": dict(options),
        "mean_iterations": float(nl.iterations[sc.mask].mean()),
        "seconds": dt,
    }


@contextmanager
def copy_counter():
    """Count Warp copies (``warp.copy``, ``array.numpy``, ``warp.array(data=...)``; a call inside another counted
    one is not counted again) while inside."""
    from gpps._runtime import warp

    wp = warp()
    n = [0]
    inside = [False]  # one transfer counts once (numpy() copies through warp.copy on CUDA)
    cls = wp.array
    old_copy, old_numpy, old_init = wp.copy, cls.numpy, cls.__init__

    def counted(fn, *a, **k):
        if inside[0]:
            return fn(*a, **k)
        n[0] += 1
        inside[0] = True
        try:
            return fn(*a, **k)
        finally:
            inside[0] = False

    def copy(*a, **k):
        return counted(old_copy, *a, **k)

    def numpy(self, *a, **k):
        return counted(old_numpy, self, *a, **k)

    def init(self, *a, **k):
        if (a and a[0] is not None) or k.get("data") is not None:
            return counted(old_init, self, *a, **k)
        return old_init(self, *a, **k)

    wp.copy, cls.numpy, cls.__init__ = copy, numpy, init
    try:
        yield n
    finally:
        wp.copy, cls.numpy, cls.__init__ = old_copy, old_numpy, old_init

"""Property-based tests of the public API: every input ends in a finite result or a clear error.

For each generated input the call must either return a finite result (no NaN
or inf in normals, albedo, depth) or raise ``ValueError`` / ``TypeError``
*from gpps code* (the innermost frame of the traceback lies in the gpps
package, not in numpy, Warp or Taichi) whose message starts with the name of
the offending argument (``"images: expected ..."``).  Anything else (another
exception, a deep traceback, NaN output, a hang) fails the test.

Profiles: the default (CI) runs a few dozen inputs per test; ``pytest -m fuzz``
runs about 10,000 inputs in all (``FUZZ_EXAMPLES``) and prints the count and
time per test.
"""

from __future__ import annotations

import os
import re
import time
import traceback
import warnings
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import gpps  # noqa: E402

pytestmark = pytest.mark.fuzz

FUZZ = os.environ.get("GPPS_FUZZ") == "1"
# inputs per test: (CI, fuzz); the fuzz column adds up to 10,000
FUZZ_EXAMPLES = {
    "solve_normals": (40, 5000),
    "stream_frames": (40, 2500),
    "value_types": (40, 1250),
    "configs": (30, 700),
    "integrate": (4, 300),
    "reconstruct": (2, 100),
    "uncalibrated": (2, 150),
}
assert sum(v[1] for v in FUZZ_EXAMPLES.values()) == 10_000
GPPS_DIR = str(Path(gpps.__file__).resolve().parent)
COUNTS: dict = {}


def _settings(name):
    return settings(max_examples=FUZZ_EXAMPLES[name][1 if FUZZ else 0], deadline=None, derandomize=not FUZZ,
                    suppress_health_check=list(HealthCheck), database=None)


NAME = re.compile(r"^[A-Za-z_][\w\[\]\.\-]*(?: [\w\-]+)?: ")


def _call(name, fn):
    """Run fn(); return its result, or None after a clean gpps error. Fails on anything else."""
    c = COUNTS.setdefault(name, {"inputs": 0, "errors": 0, "results": 0, "error results": 0, "seconds": 0.0})
    c["inputs"] += 1
    t = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with np.errstate(all="ignore"):
                out = fn()
    except (ValueError, TypeError) as e:
        c["errors"] += 1
        if isinstance(e, TypeError) and "got an unexpected keyword argument" in str(e):
            return None  # Python's own check of the call's keywords, at the call (not a deep traceback)
        tb = traceback.extract_tb(e.__traceback__)
        inner = tb[-1].filename if tb else ""
        assert str(Path(inner).resolve()).startswith(GPPS_DIR), (
            f"{type(e).__name__} raised outside gpps ({inner}:{tb[-1].lineno}): {e}\n"
            + "".join(traceback.format_tb(e.__traceback__)[-3:]))
        assert NAME.match(str(e)), f"message does not name the argument: {e!r}"
        c.setdefault("by_argument", {}).setdefault(str(e).split(":")[0], 0)
        c["by_argument"][str(e).split(":")[0]] += 1
        return None
    finally:
        c["seconds"] += time.perf_counter() - t
    c["results"] += 1
    return out


def _finite(*arrays):
    for a in arrays:
        if a is None:
            continue
        a = a.numpy() if hasattr(a, "numpy") and not isinstance(a, np.ndarray) else np.asarray(a)
        assert np.all(np.isfinite(a)), "non-finite values in a result"


# ------------------------------------------------------------------ strategies

SPECIAL = [0.0, 1.0, -1.0, 1e-30, 1e30, np.nan, np.inf, -np.inf, 0.5, 65535.0]
# the valid types more often than the invalid ones, so that the success path is exercised too
DTYPES = ["float32"] * 6 + ["float64", "float64", "uint8", "uint8", "uint16", "uint16"] + [
    "int32", "int64", "complex64", "bool", "object", "float16"]


@st.composite
def arrays(draw, shape, lo=0.0, hi=1.0, dtype=None, special=0.1):
    """A numpy array of ``shape``: uniform values, some specials, a drawn dtype."""
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    a = rng.uniform(lo, hi, size=shape)
    if draw(st.floats(0, 1)) < special and a.size:
        k = draw(st.integers(1, max(1, a.size // 4)))
        idx = rng.integers(0, a.size, k)
        a.flat[idx] = rng.choice(SPECIAL, k)
    dt = dtype or draw(st.sampled_from(DTYPES))
    if dt in ("uint8", "uint16", "int32", "int64"):
        full = {"uint8": 255, "uint16": 65535}.get(dt, 1000)
        a = np.nan_to_num(a, nan=0, posinf=full, neginf=0)
        a = np.clip(np.round(a * full), 0 if dt.startswith("u") else -full, full).astype(dt)
    elif dt == "object":
        a = a.astype(object)
    else:
        a = a.astype(dt)
    return a


@st.composite
def directions(draw, n):
    mode = draw(st.sampled_from(["good", "good", "good", "behind", "raw", "coplanar", "zero"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    if mode == "raw":
        return draw(arrays((n, 3), -2, 2, dtype="float64", special=0.3))
    if mode == "zero":
        d = np.zeros((n, 3))
    elif mode == "coplanar":
        t = rng.uniform(0, 2 * np.pi, n)
        d = np.stack([np.cos(t), np.sin(t), np.zeros(n)], -1)
    else:
        slant = rng.uniform(0.05, 1.2, n)
        az = rng.uniform(0, 2 * np.pi, n)
        d = np.stack([np.sin(slant) * np.cos(az), np.sin(slant) * np.sin(az), np.cos(slant)], -1)
        if mode == "behind":
            d[0, 2] *= -1
    nrm = np.linalg.norm(d, axis=1, keepdims=True)
    return np.where(nrm > 0, d / np.where(nrm > 0, nrm, 1), d)


@st.composite
def lights(draw, n):
    kind = draw(st.sampled_from(["directional", "directional", "point", "wrong"]))
    m = draw(st.sampled_from([n, n, n, max(1, n - 1), n + 1]))
    if kind == "wrong":
        return draw(st.sampled_from([None, "directional", np.eye(3), 3.0]))
    inten = draw(st.sampled_from([None, None, np.ones((m, 3)), np.zeros((m, 3)), -np.ones((m, 3)),
                                  np.full((m, 3), np.nan)]))
    if kind == "directional":
        d = draw(directions(m))
        return lambda: gpps.DirectionalLights(d, inten)
    pos = draw(arrays((m, 3), -50, 50, dtype="float64", special=0.2))
    pos[:, 2] = -np.abs(pos[:, 2]) if draw(st.booleans()) else pos[:, 2]
    return lambda: gpps.PointLights(pos, inten)


@st.composite
def cameras(draw):
    kind = draw(st.sampled_from(["none", "ortho", "persp", "persp-bad", "wrong"]))
    if kind == "none":
        return lambda: None
    if kind == "ortho":
        ps = draw(st.sampled_from([1.0, 0.01, 0.0, -1.0, np.nan, 1e9]))
        return lambda: gpps.Orthographic(ps)
    if kind == "persp":
        f = draw(st.floats(1.0, 1e4))
        K = np.array([[f, 0, 4.0], [0, f, 4.0], [0, 0, 1.0]])
        return lambda: gpps.camera_from_K(K)
    if kind == "persp-bad":
        K = draw(arrays((3, 3), -10, 10, dtype="float64", special=0.3))
        return lambda: gpps.camera_from_K(K)
    bad = draw(st.sampled_from(["perspective", np.eye(3), 1]))
    return lambda: bad


@st.composite
def materials(draw):
    kind = draw(st.sampled_from(["none", "named", "params", "bad"]))
    if kind == "none":
        return lambda: None
    brdf = draw(st.sampled_from(list(gpps.BRDF_NAMES)))
    if kind == "named":
        return lambda: gpps.Material(brdf)
    if kind == "params":
        vals = {k: draw(st.sampled_from([v, v, 0.0, -1.0, np.nan, 1e6])) for k, v in
                (("ks", 0.5), ("shininess", 30.0), ("roughness", 0.3), ("f0", 0.5))}
        return lambda: gpps.Material(brdf, **vals)
    bad = draw(st.sampled_from(["glass", 3, {"brdf": "phong"}]))
    return lambda: bad


@st.composite
def images_and_mask(draw, n_lo=1, n_hi=6, hw_hi=10):
    n = draw(st.integers(n_lo, n_hi))
    h = draw(st.integers(1, hw_hi))
    w = draw(st.integers(1, hw_hi))
    shape = draw(st.sampled_from([(n, h, w, 3), (n, h, w, 3), (n, h, w), (n, h, w, 1), (n, h, w, 2), (h, w),
                                  (n, h, w, 3, 1)]))
    img = draw(arrays(shape, 0.0, draw(st.sampled_from([1.0, 1.0, 1e-6, 5.0]))))
    mshape = draw(st.sampled_from([(h, w), (h, w), (h, w), (w, h), (h, w, 1)]))
    mk = draw(st.sampled_from(["ones", "ones", "random", "empty", "float", "weird"]))
    if mk == "ones":
        m = np.ones(mshape, bool)
    elif mk == "empty":
        m = np.zeros(mshape, bool)
    elif mk == "random":
        m = draw(arrays(mshape, 0, 1, dtype="float64", special=0.0)) > 0.3
    elif mk == "float":
        m = draw(arrays(mshape, 0, 1, dtype="float32", special=0.2))
    else:
        m = draw(st.sampled_from([None, "mask", np.ones(mshape, complex), np.ones(mshape, object)]))
    return n, img, m


# ------------------------------------------------------------------ the properties


def _lambertian(n, h, w, rng):
    """Plausible images: a Lambertian bump field under n good lights (float32), and those lights."""
    L = _good_lights(n, rng)
    yy, xx = np.mgrid[0:h, 0:w]
    z = 0.3 * np.sin(xx / max(w, 2) * rng.uniform(1, 4)) * np.cos(yy / max(h, 2) * rng.uniform(1, 4))
    gy, gx = np.gradient(z) if min(h, w) > 1 else (np.zeros((h, w)), np.zeros((h, w)))
    nrm = np.stack([-gx, gy, np.ones_like(z)], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    shade = np.clip(np.einsum("hwc,nc->nhw", nrm, L.directions), 0, None)
    albedo = rng.uniform(0.3, 0.9, (h, w, 3))
    img = shade[..., None] * albedo[None] + rng.normal(0, 0.002, (n, h, w, 3))
    return np.clip(img, 0, None).astype(np.float32), L


def _good_lights(n, rng):
    slant = rng.uniform(0.2, 1.0, n)
    az = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(0, 0.5)
    return gpps.DirectionalLights(np.stack([np.sin(slant) * np.cos(az), np.sin(slant) * np.sin(az), np.cos(slant)], -1))


# which argument keeps its drawn (possibly bad) value; every other one is replaced by a valid value, so that
# the success path and each argument's errors are both exercised ("all": every argument as drawn)
KEEP = ["all", "all", "none", "none", "images", "mask", "lights", "camera", "material", "solver", "depth", "opts"]


@_settings("solve_normals")
@given(data=images_and_mask(), lt=st.data(), cam=cameras(), mat=materials(),
       solver=st.sampled_from(["lm", "dogleg", "bfgs", "none", "newton"]),
       robust=st.sampled_from([None, "none", "huber", "cauchy", "l1"]),
       depth=st.sampled_from([None, "ones", "zeros", "nan", "shape"]),
       opts=st.sampled_from([{}, {"starts": 1}, {"starts": 0}, {"max_iters": -1}, {"shadow_threshold": 0.5},
                             {"saturation": 0.9}, {"smoothness": 0.3}, {"bogus": 1}]),
       keep=st.sampled_from(KEEP), seed=st.integers(0, 2**31 - 1))
def test_solve_normals(data, lt, cam, mat, solver, robust, depth, opts, keep, seed):
    from gpps.flows.photometric import solve_normals

    n, img, m = data
    L = lt.draw(lights(n))
    rng = np.random.default_rng(seed)
    if keep != "all":
        good_n = max(n, 3)
        hw = (rng.integers(2, 10), rng.integers(2, 10))
        good_img, good_L = _lambertian(good_n, *hw, rng)
        if keep != "images":
            img = good_img
        n, hw = (img.shape[0], img.shape[1:3]) if np.ndim(img) >= 3 else (good_n, hw)
        if keep != "mask":
            m = rng.random(hw) > 0.2 if np.ndim(img) >= 3 else np.ones((2, 2), bool)
        if keep != "lights":
            L = good_L if keep != "images" else _good_lights(n, rng)
        if keep != "camera":
            cam = lambda: None  # noqa: E731
        if keep != "material":
            mat = lambda: gpps.Material("blinn-phong")  # noqa: E731
        if keep != "solver":
            solver, robust = "lm", None
        if keep != "depth":
            depth = None
        if keep != "opts":
            opts = {}
    hw = np.shape(img)[1:3] if np.ndim(img) >= 3 else (1, 1)
    dep = {None: None, "ones": np.ones(hw) * 10, "zeros": np.zeros(hw), "nan": np.full(hw, np.nan),
           "shape": np.ones((2, 3))}[depth]

    def run():
        return solve_normals(img, m, L() if callable(L) else L, camera=cam(), material=mat(), solver=solver,
                             robust=robust, depth=dep, device="cpu", **opts)

    res = _call("solve_normals", run)
    if res is not None:
        _finite(res.normals, res.albedo, res.residual)


@_settings("reconstruct")
@given(data=images_and_mask(n_lo=2, n_hi=5, hw_hi=8), lt=st.data(), cam=cameras(),
       mat=st.sampled_from(["blinn-phong", "lambertian", "cook-torrance", "metal"]),
       rounds=st.sampled_from([1, 2, 0]), keep=st.sampled_from(["all", "none", "none", "images", "mask", "lights",
                                                                "camera", "material", "rounds"]),
       seed=st.integers(0, 2**31 - 1))
def test_reconstruct(data, lt, cam, mat, rounds, keep, seed):
    n, img, m = data
    L = lt.draw(lights(n))
    if keep != "all":
        rng = np.random.default_rng(seed)
        hw = (int(rng.integers(6, 12)), int(rng.integers(6, 12)))
        good_img, good_L = _lambertian(max(n, 3), *hw, rng)
        if keep != "images":
            img, n = good_img, good_img.shape[0]
        if keep != "mask":
            m = np.ones(np.shape(img)[1:3], bool) if np.ndim(img) >= 3 else np.ones((2, 2), bool)
        if keep != "lights":
            L = good_L if keep != "images" else _good_lights(max(n, 1), rng)
        if keep != "camera":
            cam = lambda: None  # noqa: E731
        if keep != "material":
            mat = "blinn-phong"
        if keep != "rounds":
            rounds = 2

    def run():
        return gpps.reconstruct(img, m, L() if callable(L) else L, camera=cam(), material=mat,
                                reference_depth=10.0, config=gpps.RONConfig(rounds=rounds), device="cpu")

    res = _call("reconstruct", run)
    if res is not None:
        _finite(res.normals, res.albedo, res.depth)


@_settings("integrate")
@given(h=st.integers(1, 12), w=st.integers(1, 12), nd=st.data(), cam=cameras(),
       solver=st.sampled_from(["multigrid", "jacobi", "direct", "dct", "cg"]),
       robust=st.sampled_from(["none", "curl", "cauchy", "bogus"]), bilateral=st.booleans(),
       ref=st.sampled_from([None, 5.0, 0.0, -1.0, np.nan]))
def test_integrate(h, w, nd, cam, solver, robust, bilateral, ref):
    from gpps.flows.integrate import integrate_normals

    mode = nd.draw(st.sampled_from(["unit", "raw", "back"]))
    if mode == "raw":
        normals = nd.draw(arrays((h, w, 3), -1, 1, special=0.3))
    else:
        rng = np.random.default_rng(nd.draw(st.integers(0, 2**31 - 1)))
        v = rng.normal(size=(h, w, 3)) * 0.3 + (0, 0, 1 if mode == "unit" else -1)
        normals = v / np.linalg.norm(v, axis=-1, keepdims=True)
    m = nd.draw(st.sampled_from([np.ones((h, w), bool), np.ones((h, w), bool), np.zeros((h, w), bool),
                                 np.ones((w, h), bool), np.random.default_rng(1).random((h, w)) > 0.3]))
    if nd.draw(st.booleans()):  # the other arguments valid: exercise the success path
        cam, solver, robust, ref = (lambda: None), "multigrid", "none", None

    def run():
        return integrate_normals(normals, m, camera=cam(), solver=solver, robust=robust, bilateral=bilateral,
                                 reference_depth=ref, device="cpu")

    res = _call("integrate", run)
    if res is not None:
        _finite(res.depth)


_STREAMS: dict = {}


def _stream(n, shape, c):
    from gpps.pipeline.stream import Stream, StreamConfig
    from gpps.flows.synthetic import default_lights

    key = (n, shape, c)
    if key not in _STREAMS:
        _STREAMS[key] = Stream(shape, gpps.Orthographic(), default_lights("directional", n),
                               gpps.Material.default_for("blinn-phong"),
                               config=StreamConfig(output="numpy", integrate=c), device="cpu")
    return _STREAMS[key]


@_settings("stream_frames")
@given(n=st.sampled_from([3, 4]), integ=st.booleans(), fr=st.data())
def test_stream_frames(n, integ, fr):
    """Frames of every shape, dtype and value: an error result or a finite one; the stream goes on."""
    shape = (8, 8)
    s = _stream(n, shape, integ)
    fshape = fr.draw(st.sampled_from([(n, 8, 8, 3), (n, 8, 8, 3), (n, 8, 8), (n, 8, 8, 1), (n - 1, 8, 8, 3),
                                      (n, 8, 9, 3), (8, 8)]))
    if fr.draw(st.booleans()):  # a plausible frame: a lit smooth surface, noise, quantisation
        rng = np.random.default_rng(fr.draw(st.integers(0, 2**31 - 1)))
        yy, xx = np.mgrid[0:8, 0:8] / 8.0
        base = 0.2 + 0.5 * (0.5 + 0.5 * np.sin(3 * xx + rng.uniform(0, 6)) * np.cos(2 * yy))
        f = np.clip(base[None, ..., None] * rng.uniform(0.3, 1.0, (n, 1, 1, 3)) + rng.normal(0, 0.01, (n, 8, 8, 3)), 0, 1)
        dt = fr.draw(st.sampled_from(["uint8", "uint16", "float32"]))
        frame = (np.round(f * {"uint8": 255, "uint16": 65535}[dt]).astype(dt) if dt != "float32"
                 else f.astype(np.float32))
    else:
        frame = fr.draw(arrays(fshape, 0, fr.draw(st.sampled_from([1.0, 1.0, 0.0, 2.0, 1e-4]))))

    def run():
        r = s.run(frame)
        if not r.ok:
            assert NAME.match(r.error), r.error  # an error result names what was wrong
        return r

    r = _call("stream_frames", run)
    if r is not None and r.ok:
        _finite(r.normals, r.albedo, r.depth)
    elif r is not None:
        COUNTS["stream_frames"]["error results"] += 1


@_settings("value_types")
@given(lt=st.data(), cam=cameras(), mat=materials(), n=st.integers(0, 5))
def test_value_types(lt, cam, mat, n):
    """Lights, cameras and materials from any values: constructed, or a clear error."""
    L = lt.draw(lights(max(n, 1)))
    for f in (L if callable(L) else (lambda: gpps.DirectionalLights(L)), cam, mat):
        obj = _call("value_types", f)
        if obj is not None and hasattr(obj, "backproject"):  # a camera: back-project a depth map
            d = np.full((3, 4), 2.0)
            _finite(_call("value_types", lambda: obj.backproject(d)))


@_settings("configs")
@given(which=st.sampled_from(["SolverConfig", "RONConfig", "StreamConfig", "IntegratorConfig", "FolderConfig",
                              "UncalibratedConfig", "SingleConfig", "CuckooConfig"]), kv=st.data())
def test_configs(which, kv):
    """Every config field with wrong values: a ValueError/TypeError naming the field."""
    import dataclasses

    from gpps.pipeline.integration import IntegratorConfig
    from gpps.pipeline.solver import SolverConfig

    cls = {"SolverConfig": SolverConfig, "RONConfig": gpps.RONConfig, "StreamConfig": gpps.StreamConfig,
           "IntegratorConfig": IntegratorConfig, "FolderConfig": gpps.FolderConfig,
           "UncalibratedConfig": gpps.UncalibratedConfig, "SingleConfig": gpps.SingleConfig,
           "CuckooConfig": gpps.CuckooConfig}[which]
    fields = [f.name for f in dataclasses.fields(cls)]
    name = kv.draw(st.sampled_from(fields + ["no_such_field"]))
    value = kv.draw(st.sampled_from([None, -1, 0, 1, 2.5, -0.5, np.nan, np.inf, "x", "lm", True, (), 10**9]))
    _call("configs", lambda: cls(**{name: value}))


@_settings("uncalibrated")
@given(data=images_and_mask(n_lo=2, n_hi=7, hw_hi=14))
def test_solve_uncalibrated(data):
    from gpps.flows.uncalibrated import solve_uncalibrated

    n, img, m = data
    if np.ndim(img) == 4 and img.shape[0] >= 3 and np.ndim(m) == 2 and np.shape(m) == img.shape[1:3] \
            and np.size(m) >= 64 and data[0] % 2 == 1:  # plausible images of the same size (success path)
        img, _ = _lambertian(img.shape[0], *img.shape[1:3], np.random.default_rng(int(img.size)))
        m = np.ones(img.shape[1:3], bool)
    res = _call("uncalibrated", lambda: solve_uncalibrated(img, m, device="cpu"))
    if res is not None:
        _finite(res.normals, res.albedo)


def teardown_module(module):
    if FUZZ:
        total = sum(c["inputs"] for c in COUNTS.values())
        lines = [f"{k:>16}: {c['inputs']:6d} inputs, {c['errors']:6d} clean errors, {c['results']:6d} results "
                 f"({c['error results']} of them error results), {c['seconds']:8.1f} s" for k, c in COUNTS.items()]
        print("\nfuzz profile:\n" + "\n".join(lines) + f"\n{'total':>16}: {total} inputs")
        for k, c in COUNTS.items():
            top = sorted(c.get("by_argument", {}).items(), key=lambda kv: -kv[1])[:8]
            print(f"{k:>16}: errors by argument {top}")

"""Shared helpers of the perf scripts: device-synchronised median timing, JSON output, and DiLiGenT subsets."""

from __future__ import annotations

import json
import os
import platform
import shutil
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))
RESULTS = ROOT / "perf" / "results"


def timeit(fn, sync, *, warmup: int = 3, repeat: int = 20, min_time: float = 0.0) -> dict:
    """Median / IQR wall time of ``fn()`` in seconds, synchronising the device around each call."""
    for _ in range(warmup):
        fn()
    sync()
    ts = []
    t_start = time.perf_counter()
    while len(ts) < repeat or time.perf_counter() - t_start < min_time:
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t0)
    ts.sort()
    q = statistics.quantiles(ts, n=4) if len(ts) >= 4 else [ts[0], statistics.median(ts), ts[-1]]
    return {"median_s": statistics.median(ts), "iqr_s": q[2] - q[0], "runs": len(ts)}


def device_label(device: str) -> str:
    if device.startswith("cuda"):
        from gpps._runtime import warp

        return warp().get_device(device).name.replace(" ", "_")
    return f"cpu-{platform.machine()}-{os.cpu_count()}cores"


def write_results(name: str, device: str, payload: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}_{device_label(device)}.json"
    payload = {"device": device, "device_name": device_label(device), "host": platform.node(), **payload}
    path.write_text(json.dumps(payload, indent=2) + "\n")
    return path


def rss_mb() -> float:
    """Resident set size of this process (MB), from /proc/self/statm."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def uint16_frame(images):
    """A camera's 16-bit view of rendered (N, H, W, 3) images: clipped to [0, 1], rounded, RGB kept.

    The frames stay RGB on purpose: averaged to grey, the bumps scene's 3 Blinn-Phong
    observations per pixel no longer determine the normal.  Grey leaves 3 equations for 3
    unknowns (2 for the normal, 1 albedo) and the specular lobe gives them other exact
    roots: 32 % of the pixels of the 48^2 scene then fit the grey data to 2e-6 with normals
    more than 1 deg off (MAEN 6.1 deg, offline and stream alike).  In RGB the white highlight
    and the coloured albedo differ between channels (9 equations, 5 unknowns): 0.006 deg.
    The bench reported 5.96-5.98 deg from grey frames until this was found (issue 20).
    """
    import numpy as np

    return np.ascontiguousarray(np.round(np.clip(images, 0, 1) * 65535).astype(np.uint16))


def bumps_frame(size: int, device: str, shift: int = 0, material=None):
    """The benchmarks' scene: Blinn-Phong bumps, perspective, 3 directional lights, moved ``shift`` pixels right.

    ``material``: another :class:`gpps.Material` to render with (default: Blinn-Phong's defaults).

    Returns:
        ``(scene, material, lights, frame)``: the moved scene, the material and lights
        (intensities included), and its (3, H, W, 3) uint16 RGB frame (:func:`uint16_frame`).
    """
    import numpy as np

    from gpps.flows.synthetic import default_lights, render
    from gpps.host.scenes import make_scene
    from gpps.material import Material

    mat = Material.default_for("blinn-phong") if material is None else material
    L = default_lights("directional", 3)
    sc = make_scene("bumps", size, "perspective")
    if shift:
        sc = type(sc)(**{n: (np.roll(v, shift, axis=1) if isinstance(v, np.ndarray) and v.ndim >= 2 else v)
                         for n, v in sc.__dict__.items()})
    return sc, mat, L, uint16_frame(render(sc, mat, L, bits=16, device=device))


def reconstruct_inputs(size: int, n: int, device) -> dict:
    """Issue 20's synthetic capture (as ``perf/reconstruct_synthetic.py``): Cook-Torrance bumps (ks 0.8,
    roughness 0.2), perspective, ``n`` directional lights, 16-bit, divided by the light intensities (its clipped
    highlights, 1.5-3.8 % of the observations at 3 lights, sit at 1 / 0.8 = 1.25; the pipeline finds and leaves them
    out since session 24, :mod:`gpps.host.clipping`: MAEN 1.42 -> 0.0085 deg at 256^2).  Returns
    ``images``, ``mask``, ``lights`` (unit intensities), ``camera`` and the true ``normals``."""
    import gpps

    sc = gpps.make_scene("bumps", size, "perspective")
    L = gpps.default_lights("directional", n, layout="ring" if n <= 4 else "spiral")
    true = gpps.Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)
    img = gpps.render(sc, true, L, bits=16, device=device) / L.intensities[:, None, None, :]
    return {"images": img, "mask": sc.mask, "lights": gpps.DirectionalLights(L.directions), "camera": sc.camera,
            "normals": sc.normals, "material": true}


def reconstruct_case(size: int, n: int, device):
    """:func:`reconstruct_inputs`'s capture with the material unknown.  Returns ``call() -> (Reconstruction, maen)``
    where ``maen()`` measures the error after the caller's clock stops (the benchmark's work, not the pipeline's)."""
    import gpps

    c = reconstruct_inputs(size, n, device)

    def call():
        rec = gpps.reconstruct(c["images"], c["mask"], c["lights"], camera=c["camera"], material="cook-torrance",
                               device=device)
        return rec, lambda: float(gpps.normal_errors(rec.normals, c["normals"], c["mask"])["mean"])
    return call


def reconstructor_case(size: int, n: int, device, *, known: bool = False):
    """:func:`reconstruct_case` through one kept ``gpps.Reconstructor`` (its stages built at the first call and kept):
    ``call() -> (Reconstruction, maen)``; ``call.close()`` releases the stages.  ``known``: the rendered material
    given (:func:`reconstruct_inputs`' rendered one: no estimation)."""
    import gpps

    c = reconstruct_inputs(size, n, device)
    mat = c["material"] if known else "cook-torrance"
    rc = gpps.Reconstructor(c["mask"], c["lights"], camera=c["camera"], material=mat, device=device)

    def call():
        rec = rc(c["images"])
        return rec, lambda: float(gpps.normal_errors(rec.normals, c["normals"], c["mask"])["mean"])
    call.close = rc.close
    return call


def moving_bumps(size: int, device: str, positions: int = 8, material=None):
    """The stream benchmarks' scene: Blinn-Phong bumps, perspective, 3 directional lights, moved sideways.

    ``material``: another :class:`gpps.Material` to render with (the full mode's scene: Cook-Torrance).

    Returns:
        ``(scene, material, lights, frames, truth, mask)``: ``positions`` uint16 RGB
        frames (N, H, W, 3) of the object moved by 0..positions-1 pixels
        (:func:`bumps_frame`), their true normals, and the mask of the pixels inside the
        object at every position.
    """
    import numpy as np

    frames, truth = [], []
    sc = mat = L = mask = None
    for k in range(positions):
        moved, mat, L, frame = bumps_frame(size, device, shift=k, material=material)
        if k == 0:
            sc, mask = moved, moved.mask.copy()
        frames.append(frame)
        truth.append(moved.normals.astype(np.float32))
        mask &= moved.mask
    return sc, mat, L, frames, truth, mask


def best_triple(directions) -> tuple[int, int, int]:
    """Indices of the 3 light directions with the largest |det| (the best-conditioned triple for photometric
    stereo)."""
    import numpy as np

    d = np.asarray(directions, dtype=np.float64)
    best, arg = -1.0, (0, 1, 2)
    n = len(d)
    for i in range(n):
        for j in range(i + 1, n):
            c = np.cross(d[i], d[j])
            v = np.abs(d[j + 1:] @ c)
            if v.size and v.max() > best:
                best = float(v.max())
                arg = (i, j, j + 1 + int(v.argmax()))
    return arg


def diligent_subset(src: Path, dst: Path, idx) -> Path:
    """``dst`` holding the images ``idx`` (0-based) of the DiLiGenT folder ``src`` with the matching light rows,
    its K, mask and ground-truth normals."""
    import numpy as np

    src, dst = Path(src), Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    names = [s.strip() for s in (src / "filenames.txt").read_text().split() if s.strip()]
    idx = [int(k) for k in idx]
    for k in idx:
        shutil.copy(src / names[k], dst / names[k])
    (dst / "filenames.txt").write_text("\n".join(names[k] for k in idx) + "\n")
    for f in ("light_directions.txt", "light_intensities.txt"):
        np.savetxt(dst / f, np.loadtxt(src / f)[idx])
    for f in ("K.txt", "normal_gt.npy", "mask.png"):
        shutil.copy(src / f, dst / f)
    return dst


def folder_solve(folder, device):
    """The folder flow's reconstruction of ``folder`` with the compensation asked for, stopped before its first
    gather: ``(solve, first)``, the flow's ``solve(images) -> Reconstruction`` (later calls are the compensation's
    later reconstructions: the first's model kept, its material refined) and the first reconstruction (of the
    observed images).  For probes that run their own compensation rounds (perf/glossy_interreflection_probe.py,
    perf/interreflection_oracle_probe.py)."""
    import gpps
    import gpps.flows.interreflection as gi

    captured = {}
    orig = gi.reconstruct_subtracting

    def grab(solve, images, *args, **kw):
        captured["solve"] = solve
        captured["first"], _ = orig(solve, images, *args, **{**kw, "rounds": 0})
        return captured["first"], _

    gi.reconstruct_subtracting = grab
    try:
        gpps.reconstruct_folder(folder, gpps.FolderConfig(interreflections="subtract"), device=device)
    finally:
        gi.reconstruct_subtracting = orig
    return captured["solve"], captured["first"]


def cached_captures(seeds: str, counts) -> list[str]:
    """The cached Mitsuba captures (``$GPPS_CACHE_DIR/mitsuba_captures``, perf/dev_eval.py's and
    perf/heldout_eval.py's ``--render-only``) of the comma-separated ``seeds`` under any of ``counts`` directional or
    point lights, sorted (a capture under several counts once)."""
    import glob

    out = []
    for f in sorted(glob.glob(os.path.join(os.environ.get('GPPS_CACHE_DIR', '.cache'), 'mitsuba_captures', '*'))):
        name = os.path.basename(f)
        if any(f'seed{s}-' in name for s in seeds.split(',')) and any(
                f'-directional{c}-' in name or f'-point{c}-' in name for c in counts):
            out.append(f)
    return out

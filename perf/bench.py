"""Offline kernel benchmark: every per-frame kernel of gpps against the device's roofline.

For each size (default 256^2, 512^2, 1024^2, 2048^2) on the chosen device, a
perspective Blinn-Phong scene (``bumps``, 3 directional lights, 16-bit frames):

* ``brdf``: image formation (render kernel, 3 lights);
* ``residual_jacobian``: one variable-projection evaluation (cost, J^T r, J^T J) per pixel;
* ``lm_iteration`` / ``dogleg_iteration``: one solver iteration, from the
  difference of warm solves with 5 and 1 iterations (fixed work, no early exit);
* ``solve_warm``: the streaming solve (1 start, 4 evaluations); ``solve_cold``: 10 starts, to convergence;
* ``pcg_iteration``: one fused multigrid-preconditioned CG iteration of the integrator (the V-cycle is in it);
* ``integration_cold``: integration to relative residual 1e-4 from zero;
  ``integration_warm``: the streaming integration (2 iterations, warm);
* ``frame_device``: the whole :class:`gpps.pipeline.stream.Stream` frame with the
  uint16 RGB triple already on the device; ``frame_host``: with the upload of a host uint16 triple;
  the last stream row carries ``maen_stream`` (the stream's normals against the truth) and
  ``maen_offline`` (the cold multi-start solve of the same quantised frame: the figure it should equal);
* ``moving_stream`` (at the smallest size by default, ``--moving-sizes``): the stream on the moving
  scene of ``perf/_common.moving_bumps`` (the object moves one pixel a frame, back and forth over
  ``--moving-positions`` positions, ``--moving-frames`` frames), its MAEN per frame beside the offline
  ``gpps.solve_normals`` and ``gpps.reconstruct`` (material known) of the same frames.

The stream gets RGB frames, as a colour camera gives them: grey frames (the RGB mean) of this
3-light scene leave each pixel 3 observations for 3 unknowns, and the Blinn-Phong lobe gives
them spurious exact roots (6 deg MAEN offline and in the stream alike; see
``_common.uint16_frame``).  Until issue 20 the bench gave the stream such grey frames and
reported 5.96-5.98 deg.

Timing: median over repeats after warm-up, device-synchronised; a Warp kernel
is timed as ``inner`` back-to-back launches inside a CUDA graph (on CUDA) so the
launch overhead does not hide the kernel, Taichi kernels as back-to-back
launches.  Bytes and FLOPs are counted by hand per pixel (documented in
``COUNTS``: an add, multiply or compare is 1 FLOP, an FMA 2, a sqrt, division,
exp or log 1 -- the transcendental units make those cheap in throughput terms,
so the FLOP bound is a lower bound).  The roofline is measured in the same
run: copy bandwidth (``wp.copy`` of 512 MiB) and an FMA-chain FLOP probe.
``ratio`` = measured time / max(bytes / bandwidth, FLOPs / peak) (1 = at the bound).

Writes ``perf/results/bench_<device>.json`` and prints a table last (progress goes to stderr).

The offline chain (``--chain``; rows, scene and counts in ``perf/_bench_chain.py``): the kernels the
stream skips, on a DiLiGenT-ball-like scene (perspective Blinn-Phong sphere, ``--chain-size`` 166,
``--chain-images`` 96 spiral lights): DGMC on the device (the highlight test, one geodesic min-plus
sweep, the start search 4.17-4.18, and the whole step), the material scorer's batched solve (K = 25
candidates x P = 2000 samples, at 96 and at 3 images), the full-image pixel solve (the offline normals
step) and BiNI's CG iteration; same timing and ratio, bytes counted as compulsory traffic, float64
kernels against a float64 FMA probe.  ``--chain`` alone runs only those rows (``--sizes`` adds the
stream's) and writes ``perf/results/bench_chain_<device>.json`` (default sizes: the above on CUDA, 48^2,
12 images, K = 9 x P = 200 on the single-threaded CPU backend).  ``--ncu-driver K`` times nothing: it
sets every chain kernel up, then launches each K times outside graphs inside one CUDA profiler range
(``perf/ncu_chain.py`` runs it under Nsight Compute) and writes the launch order to ``--out``.

Usage:  python perf/bench.py [--device cuda:0] [--sizes 256 512 1024 2048] [--repeat 20]
        python perf/bench.py --device cuda:0 --chain [--chain-size 166 --chain-images 96 --chain-samples 2000
            --chain-candidates 25]   (the defaults on CUDA; on the CPU 48, 12, 200, 9)
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

N_LIGHTS = 3
# per pixel, by hand (see each kernel): bytes moved to/from device memory, FLOPs
COUNTS = {
    # reads depth 4 + normal 12 + mask 1 + albedo 12, writes N x 12
    # per light: view/light/half vectors and dots ~40, Blinn-Phong lobe (exp/log1p form) ~25, combine 3 ch ~10
    "brdf": lambda n: (29 + 12 * n, 20 + 75 * n),
    # reads N images (12) + N weights (4) + depth 4 + normal 12, writes 4; two passes over the lights
    # (light_terms: lobe value + gradient ~110, diffuse ~15, chart derivatives ~12) and 3-channel
    # normal equations / residuals ~60 per light and pass; chart, 2x2 algebra ~60
    "residual_jacobian": lambda n: (16 * n + 20, 60 + 2 * n * (140 + 60)),
    # one more evaluation and a 2x2 solve, data in registers/L1 except the images and weights
    "iteration": lambda n: (16 * n, 2 * n * (140 + 60) + 120),
    # per pixel per PCG iteration (all levels, 4/3 of the fine level): 2+2 Jacobi sweeps, residual,
    # restrict, prolong (~28 B and ~12 FLOP per point each), CG: A p, 3 dots, 4 axpys (~60 B, ~30 FLOP)
    "pcg_iteration": lambda n: (int(4 / 3 * 7 * 28) + 60, int(4 / 3 * 7 * 12) + 30),
}


def _median_time(fn, sync, repeat, inner=1, warmup=2):
    for _ in range(warmup):
        fn()
    sync()
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        sync()
        ts.append((time.perf_counter() - t0) / inner)
    return statistics.median(ts)


def _graph_time(wp, launch, device, repeat, inner=20):
    """Device time of ``launch`` from a CUDA graph of ``inner`` launches (CPU: plain launches)."""
    if not device.startswith("cuda"):
        return _median_time(launch, lambda: wp.synchronize_device(device), repeat, inner=1)
    launch()
    wp.synchronize_device(device)
    wp.capture_begin(device=device)
    try:
        for _ in range(inner):
            launch()
    finally:
        g = wp.capture_end(device=device)
    return _median_time(lambda: wp.capture_launch(g), lambda: wp.synchronize_device(device), repeat) / inner


def roofline(wp, device, repeat, f64=False):
    """Copy bandwidth (bytes read + written per second) and FMA-chain FLOP/s (and float64 FLOP/s with ``f64``)."""
    n = (512 << 20) // 4 if device.startswith("cuda") else (64 << 20) // 4
    a = wp.zeros(n, dtype=wp.float32, device=device)
    b = wp.zeros(n, dtype=wp.float32, device=device)
    t = _median_time(lambda: wp.copy(b, a), lambda: wp.synchronize_device(device), repeat, inner=5)
    bw = 2 * 4 * n / t
    from _bench_kernels import fma_peak

    threads = 1 << 22 if device.startswith("cuda") else 1 << 12
    steps = 256
    out = wp.zeros(threads, dtype=wp.float32, device=device)
    tf = _median_time(lambda: wp.launch(fma_peak, dim=threads, inputs=[out, steps], device=device),
                      lambda: wp.synchronize_device(device), max(3, repeat // 4))
    if not f64:
        return bw, threads * steps * 16 / tf
    from _bench_kernels import fma_peak_f64

    out64 = wp.zeros(threads, dtype=wp.float64, device=device)
    t64 = _median_time(lambda: wp.launch(fma_peak_f64, dim=threads, inputs=[out64, steps], device=device),
                       lambda: wp.synchronize_device(device), max(3, repeat // 4))
    return bw, threads * steps * 16 / tf, threads * steps * 16 / t64


def bench_size(size, device, repeat, bw, peak, log):
    import numpy as np
    from _common import bumps_frame

    from gpps._runtime import warp
    from gpps.material import Material
    from gpps.pipeline.render import Renderer
    from gpps.pipeline.solver import PixelSolver, SolverConfig
    from gpps.pipeline.stream import Stream, StreamConfig

    wp = warp()
    sync = lambda: wp.synchronize_device(device)
    rows = []
    t0 = time.perf_counter()
    # the stream's frame: the camera's uint16 RGB view (grey frames are ambiguous here: _common.uint16_frame)
    sc, mat, L, frame16 = bumps_frame(size, device)
    assert len(L) == N_LIGHTS and mat == Material.default_for("blinn-phong")
    npx = size * size
    log(f"[{size}] scene {time.perf_counter() - t0:.1f}s")

    def row(name, seconds, count_key=None, extra=None, per=1.0):
        r = {"size": size, "kernel": name, "seconds": seconds}
        if count_key is not None:
            bpp, fpp = COUNTS[count_key](N_LIGHTS)
            by, fl = bpp * npx * per, fpp * npx * per
            bound = max(by / bw, fl / peak)
            r.update(bytes=by, flops=fl, gbps=by / seconds / 1e9, gflops=fl / seconds / 1e9,
                     bound_s=bound, ratio=seconds / bound, limited_by="memory" if by / bw >= fl / peak else "compute")
        if extra:
            r.update(extra)
        rows.append(r)
        log(f"[{size}] {name:20s} {seconds * 1e3:9.3f} ms" + (f"  ratio {r['ratio']:.2f}" if "ratio" in r else ""))
        return r

    # ---- BRDF evaluation
    rd = Renderer((size, size), sc.camera, L, mat, device=device)
    rd.upload(sc.depth, sc.mask, sc.albedo, normals=sc.normals)
    rd.step()
    from gpps.kernels import render as rk

    def launch_render():
        wp.launch(rk.render_kernel, dim=(size, size),
                  inputs=[rd.depth, rd.normals, rd.mask, rd.albedo, rd.cam, rd.lp, rd.mp], outputs=[rd.images],
                  device=device)

    row("brdf", _graph_time(wp, launch_render, device, repeat), "brdf")
    # the solver rows see the stream's frame, converted as the stream converts it
    img_np = frame16.astype(np.float32) / 65535 / np.asarray(L.intensities, np.float32)[:, None, None, :]

    # ---- residual + Jacobian
    from gpps.lights import DirectionalLights

    Lu = DirectionalLights(L.directions)
    ps = PixelSolver((N_LIGHTS, size, size), sc.camera, Lu, mat, SolverConfig(), device=device)
    ps.upload(img_np, sc.mask)
    ps.step()
    sync()
    from _bench_kernels import evaluate_kernel

    cost = wp.zeros((size, size), dtype=wp.float32, device=device)

    def launch_eval():
        wp.launch(evaluate_kernel, dim=(size, size),
                  inputs=[ps.images, ps.weights, ps.depth, ps.normals, ps.cam, ps.lp, ps.mp, ps.prm],
                  outputs=[cost], device=device)

    row("residual_jacobian", _graph_time(wp, launch_eval, device, repeat), "residual_jacobian")

    # ---- solver iterations: warm solves with 1 and 5 iterations
    for solver in ("lm", "dogleg"):
        ts = {}
        for k in (1, 5):
            ps.set_config(SolverConfig(solver=solver, warm_start=True, starts=1, max_iters=k, early_exit=False,
                                       neighbour_radius=0))
            ts[k] = _graph_time(wp, ps.step, device, repeat, inner=5)
        row(f"{solver}_iteration", (ts[5] - ts[1]) / 4, "iteration", {"solve_1_iter_s": ts[1], "solve_5_iter_s": ts[5]})
    ps.set_config(SolverConfig(warm_start=True, starts=1, max_iters=3, early_exit=False, neighbour_radius=0))
    row("solve_warm", _graph_time(wp, ps.step, device, repeat, inner=5), "iteration", per=4.0,
        extra={"note": "the stream's solve: 1 warm start, 3 iterations (4 evaluations) + observation weights"})
    ps.set_config(SolverConfig())
    ps.upload(img_np, sc.mask)
    tc = _median_time(ps.step, sync, max(3, repeat // 4), warmup=1)
    out = ps.fetch()
    row("solve_cold", tc, extra={"mean_evaluations": float(out["iterations"][sc.mask].mean())})
    from gpps.host.metrics import normal_errors

    maen_offline = normal_errors(out["normals"], sc.normals, sc.mask)["mean"]

    # ---- integration
    from gpps.pipeline.integration_device import StreamIntegrator

    si = StreamIntegrator(sc.mask, sc.camera, device="cuda:0" if device.startswith("cuda") else "cpu")
    if device.startswith("cuda"):
        nrm = wp.to_torch(wp.array(sc.normals.astype(np.float32), dtype=wp.vec3, device=device))
        dep = wp.to_torch(wp.zeros((size, size), dtype=wp.float32, device=device))
    else:
        nrm = np.ascontiguousarray(sc.normals, np.float32)
        dep = np.zeros((size, size), np.float32)
    from gpps import _taichi

    tsync = _taichi.ti.sync
    si.step(nrm, dep, tol=1e-4)
    tsync()
    K = si._K
    row("pcg_iteration", _median_time(K["pcg_iteration"], tsync, repeat, inner=10), "pcg_iteration")

    def cold():
        si.reset()
        si.step(nrm, dep, tol=1e-4)

    tcold = _median_time(cold, tsync, max(3, repeat // 4), warmup=1)
    its = si.last_iterations
    row("integration_cold", tcold, extra={"iterations": its, "tol": 1e-4, "residual": si.last_residual})
    tw = _median_time(lambda: si.step(nrm, dep, iterations=2), tsync, repeat)
    row("integration_warm", tw, extra={"iterations": 2, "residual_after": si.residual()})
    # accuracy of the cold solution against the true depth (scale-aligned)
    d = dep.cpu().numpy() if hasattr(dep, "cpu") else dep
    m = sc.mask
    dd = d * np.exp(np.mean(np.log(sc.depth[m])) - np.mean(np.log(np.maximum(d[m], 1e-30))))
    rows[-1]["depth_error_rel_range"] = float(np.abs(dd - sc.depth)[m].mean() / np.ptp(sc.depth[m]))
    si.close()

    # ---- whole frames through the stream
    st = Stream((size, size), sc.camera, L, mat, mask=sc.mask, config=StreamConfig(), device=device)
    fdev = wp.array(frame16, dtype=wp.uint16, device=device)
    for _ in range(4):
        r = st.run(fdev)
        assert r.ok, r.error
    sync()
    tdev = _median_time(lambda: st.run(fdev), sync, repeat)
    row("frame_device", tdev, extra={"triples_per_s": 1.0 / tdev})
    thost = _median_time(lambda: st.run(frame16), sync, repeat)
    row("frame_host", thost, extra={"triples_per_s": 1.0 / thost, "frame_bytes": int(frame16.nbytes)})
    st1 = Stream((size, size), sc.camera, L, mat, mask=sc.mask, config=StreamConfig(integration_iterations=1),
                 device=device)
    for _ in range(4):
        st1.run(fdev)
    sync()
    t1 = _median_time(lambda: st1.run(fdev), sync, repeat)
    row("frame_device_1pcg", t1, extra={"triples_per_s": 1.0 / t1, "note": "1 PCG iteration per frame"})
    frames = [frame16] * max(repeat, 10)
    sync()
    t = time.perf_counter()
    nres = sum(1 for _ in st.iterate(frames))
    sync()
    trun = (time.perf_counter() - t) / nres
    row("frame_host_pipelined", trun, extra={"triples_per_s": 1.0 / trun, "note": "Stream.run: next upload overlaps"})
    rr = st.run(fdev).numpy()
    rows[-1]["maen_stream"] = normal_errors(rr.normals, sc.normals, sc.mask)["mean"]
    rows[-1]["maen_offline"] = maen_offline
    log(f"[{size}] MAEN stream {rows[-1]['maen_stream']:.4f} deg, offline solve of the same frame {maen_offline:.4f} deg")
    return rows


def bench_moving(size, device, positions, frames, log):
    """The stream's MAEN per frame on a moving scene beside the offline solves of the same frames.

    The object of :func:`_common.moving_bumps` moves one pixel a frame, back and forth over
    ``positions`` positions, for ``frames`` frames (numpy output: the normals come back every
    frame).  Offline, each position's frame is solved once by ``gpps.solve_normals`` (10 cold
    starts) and by ``gpps.reconstruct`` (DGMC starts, material known: nothing to estimate);
    every MAEN is over the mask of the pixels inside the object at every position.

    Returns:
        one row (``kernel="moving_stream"``, ``seconds``: median host time of a stream frame).
    """
    import numpy as np
    from _common import moving_bumps

    import gpps
    from gpps.flows.ron import RONConfig
    from gpps.host.metrics import normal_errors
    from gpps.pipeline.integration import IntegratorConfig
    from gpps.pipeline.stream import Stream, StreamConfig

    t0 = time.perf_counter()
    sc, mat, L, fr, truth, mask = moving_bumps(size, device, positions)
    path = list(range(positions)) + list(range(positions - 2, 0, -1))  # 0..P-1..1, then again
    seq = [path[i % len(path)] for i in range(frames)]
    log(f"[{size}] moving scene: {positions} positions {time.perf_counter() - t0:.1f}s")
    unit = gpps.DirectionalLights(L.directions)
    inten = np.asarray(L.intensities, np.float32)[:, None, None, :]
    same = RONConfig(integrator=IntegratorConfig(tol=1e-5, weighting="uniform"))
    solve, recon = [], []
    t0 = time.perf_counter()
    for p in range(positions):
        img = fr[p].astype(np.float32) / 65535 / inten  # what the stream's conversion gives its solver
        sn = gpps.solve_normals(img, mask, unit, camera=sc.camera, material=mat, device=device)
        solve.append(normal_errors(sn.normals, truth[p], mask)["mean"])
        rc = gpps.reconstruct(img, mask, unit, camera=sc.camera, material=mat, config=same, device=device)
        recon.append(normal_errors(rc.normals, truth[p], mask)["mean"])
    t_off = (time.perf_counter() - t0) / positions
    st = Stream(mask.shape, sc.camera, L, mat, mask=mask, config=StreamConfig(output="numpy"), device=device)
    maen, secs, errors = [], [], 0
    for p, r in zip(seq, st.iterate(fr[p] for p in seq)):
        if not r.ok:
            errors += 1
            maen.append(float("nan"))
            continue
        maen.append(normal_errors(r.normals, truth[p], mask)["mean"])
        secs.append(r.seconds)
    per_solve = [solve[p] for p in seq]
    per_recon = [recon[p] for p in seq]
    log(f"[{size}] moving scene, MAEN per frame (deg), {frames} frames over positions {seq}:")
    log(f"[{size}]   stream         " + " ".join(f"{v:.3f}" for v in maen) + f"   mean {float(np.nanmean(maen)):.4f}")
    log(f"[{size}]   solve_normals  " + " ".join(f"{v:.3f}" for v in per_solve) + f"   mean {float(np.nanmean(per_solve)):.4f}")
    log(f"[{size}]   reconstruct    " + " ".join(f"{v:.3f}" for v in per_recon) + f"   mean {float(np.nanmean(per_recon)):.4f}")
    return {"size": size, "kernel": "moving_stream", "seconds": float(np.median(secs)) if secs else float("nan"),
            "positions": positions, "frames": frames, "position_per_frame": seq, "stream_errors": errors,
            "maen_stream_per_frame": maen, "maen_offline_per_frame": per_solve,
            "maen_reconstruct_per_frame": per_recon, "maen_stream_mean": float(np.nanmean(maen)),
            "maen_offline_mean": float(np.nanmean(per_solve)), "maen_reconstruct_mean": float(np.nanmean(per_recon)),
            "maen_stream_last": maen[-1], "offline_seconds_per_frame": t_off,
            "note": "stream (numpy output, host frames) vs offline solve_normals / reconstruct of the same uint16 "
                    "RGB frames, material known; seconds: median host time of a stream frame"}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--sizes", type=int, nargs="*", default=None,
                    help="stream rows' sizes (default 256 512 1024 2048; none with --chain)")
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--out", default=None)
    ap.add_argument("--moving-sizes", type=int, nargs="*", default=None,
                    help="sizes of the moving-scene accuracy row (default: the smallest of --sizes; none: skip)")
    ap.add_argument("--moving-positions", type=int, default=8)
    ap.add_argument("--moving-frames", type=int, default=24)
    ap.add_argument("--chain", action="store_true", help="the offline chain's kernels (perf/_bench_chain.py)")
    # the chain's sizes: CUDA: DiLiGenT-ball-like (166^2, 96 images, RON's K = 25 x P = 2000); CPU (one thread:
    # a 166^2 x 96-image solve alone takes 17 s there, the scorer's step 20 s): 48^2, 12 images, K = 9 x P = 200
    ap.add_argument("--chain-size", type=int, default=None, help="image side of the chain's scene (166; CPU 48)")
    ap.add_argument("--chain-images", type=int, default=None, help="images of the chain's scene (96; CPU 12)")
    ap.add_argument("--chain-samples", type=int, default=None, help="material scorer: sample pixels P (2000; CPU 200)")
    ap.add_argument("--chain-candidates", type=int, default=None, help="material scorer: candidates K (25; CPU 9)")
    ap.add_argument("--chain-parts", nargs="*", default=None,
                    help="some of: dgmc scorer solve lanes bini search front rounds (default all)")
    ap.add_argument("--ncu-driver", type=int, default=0, metavar="K",
                    help="no timing: launch each chain kernel K times in a CUDA profiler range (perf/ncu_chain.py)")
    a = ap.parse_args(argv)
    if a.ncu_driver:
        a.chain = True
    if a.sizes is None:
        a.sizes = [] if a.chain else [256, 512, 1024, 2048]
    moving_sizes = [min(a.sizes)] if a.moving_sizes is None and a.sizes else (a.moving_sizes or [])
    from gpps._runtime import resolve_device, warp
    from gpps.io import save_json

    wp = warp()
    device = resolve_device(a.device)
    log = lambda s: print(s, file=sys.stderr, flush=True)
    parts = a.chain_parts if a.chain_parts else None
    if a.chain:
        from _bench_chain import PARTS

        parts = parts or list(PARTS)
        bad = [p for p in parts if p not in PARTS]
        if bad:
            ap.error(f"--chain-parts: expected some of {list(PARTS)}, got {bad}")
    for name, gpu, cpu in (("chain_size", 166, 48), ("chain_images", 96, 12), ("chain_samples", 2000, 200),
                           ("chain_candidates", 25, 9)):
        if getattr(a, name) is None:
            setattr(a, name, gpu if device.startswith("cuda") else cpu)
    from _common import device_label

    label = device_label(device)
    if a.ncu_driver:
        return ncu_driver(a, device, parts, log)
    bw, peak, *peak64 = roofline(wp, device, a.repeat, f64=a.chain)
    log(f"roofline: copy {bw / 1e9:.0f} GB/s, FMA {peak / 1e12:.2f} TFLOP/s"
        + (f", float64 FMA {peak64[0] / 1e12:.2f} TFLOP/s" if peak64 else ""))
    rows, errors = [], []
    for size in a.sizes:
        try:
            rows += bench_size(size, device, a.repeat, bw, peak, log)
        except Exception as e:  # keep the other sizes' numbers
            errors.append({"size": size, "error": repr(e), "trace": traceback.format_exc()})
            log(f"[{size}] FAILED: {e!r}")
    for size in moving_sizes:
        try:
            rows.append(bench_moving(size, device, a.moving_positions, a.moving_frames, log))
        except Exception as e:
            errors.append({"size": size, "kernel": "moving_stream", "error": repr(e), "trace": traceback.format_exc()})
            log(f"[{size}] moving FAILED: {e!r}")
    payload = {"device": device, "device_name": label, "copy_bandwidth_Bps": bw, "fma_peak_flops": peak,
               "n_lights": N_LIGHTS, "scene": "bumps, perspective, blinn-phong, 3 directional lights, uint16 RGB frames",
               "command": "python perf/bench.py " + " ".join(sys.argv[1:] if argv is None else argv)}
    if a.chain:
        from _bench_chain import Ctx, bench_chain

        ctx = Ctx(device, a.repeat, bw, peak, peak64[0], _median_time, _graph_time, a.chain_size)
        rows += bench_chain(ctx, parts, a.chain_images, a.chain_samples, a.chain_candidates, errors)
        payload.update(fma_peak_f64_flops=peak64[0], chain_scene=(
            f"sphere {a.chain_size}^2, perspective, blinn-phong, {a.chain_images} spiral directional lights "
            "(3: ring), 16-bit, 0.5 % noise, divided by the intensities"))
    name = f"bench_chain_{label}.json" if a.chain and not a.sizes else f"bench_{label}.json"
    path = Path(a.out) if a.out else ROOT / "perf" / "results" / name
    save_json(path, {**payload, "rows": rows, "errors": errors})
    print(f"\n{'size':>5} {'kernel':22s} {'ms':>9} {'GB/s':>8} {'GFLOP/s':>9} {'ratio':>6}  notes")
    for r in rows:
        extra = ""
        if "triples_per_s" in r:
            extra = f"{r['triples_per_s']:.0f} triples/s"
        elif "summary" in r:
            extra = r["summary"]
        elif "iterations" in r:
            extra = f"{r['iterations']} it"
        if "maen_stream_mean" in r:
            extra = (f"MAEN stream {r['maen_stream_mean']:.4f} / solve_normals {r['maen_offline_mean']:.4f} / "
                     f"reconstruct {r['maen_reconstruct_mean']:.4f} deg over {r['frames']} frames")
        elif "maen_stream" in r:
            extra += f"  MAEN stream {r['maen_stream']:.4f} / offline {r['maen_offline']:.4f} deg"
        print(f"{r['size']:5d} {r['kernel']:22s} {r['seconds'] * 1e3:9.3f} {r.get('gbps', float('nan')):8.1f} "
              f"{r.get('gflops', float('nan')):9.1f} {r.get('ratio', float('nan')):6.2f}  {extra}")
    print(f"wrote {path}")
    if errors:
        print(f"{len(errors)} part(s) FAILED (traces in the JSON): " + ", ".join(
            str(e.get("part", e.get("kernel", e["size"]))) for e in errors))


def ncu_driver(a, device, parts, log):
    """``--ncu-driver K``: set up the chain's kernels, launch each K times in a profiler range, write the order."""
    import json

    from _bench_chain import Ctx, bench_chain, launch_profiled

    nan = float("nan")
    ctx = Ctx(device, a.repeat, nan, nan, nan, _median_time, _graph_time, a.chain_size, driver=a.ncu_driver)
    errors = []
    bench_chain(ctx, parts, a.chain_images, a.chain_samples, a.chain_candidates, errors)
    manifest = launch_profiled(ctx)
    out = {"device": device, "size": a.chain_size, "images": a.chain_images, "samples": a.chain_samples,
           "candidates": a.chain_candidates, "launches": manifest, "errors": errors}
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=2) + "\n")
    log(f"[driver] {len(manifest)} kernels launched {a.ncu_driver} time(s) each; {len(errors)} part(s) failed")
    return out


if __name__ == "__main__":
    main()

"""Probe: is a warm stream-integration frame bound by the host or the device, and can one
Taichi task with software grid barriers replace the ~30 tasks of a frame? (issue 4)

1. Host against device time of the one-launch frame kernel
   (:class:`gpps.pipeline.integration_device.StreamIntegrator`, 1024^2, 1 cycle) and of
   empty kernels with and without arguments: the GPU is first put to sleep
   (``torch.cuda._sleep``) so that the host can queue ``--frames`` launches before the
   device starts; the host time of queueing them and the device time between two events
   around them (``torch.cuda.Event`` on the legacy default stream, which Taichi uses) are
   reported per launch.  A host time near the sleep means a launch waits for the device.
2. A grid barrier written in Taichi (block barrier, one arrival atomic per block, a spin
   on an atomic read, a grid memory fence on both sides) inside one task of
   ``#SMs x 256`` threads: ``P`` phases of a 5-point averaging stencil ping-ponged
   between two fields, checked against numpy, and timed per phase at 1024^2 and at 16^2
   (there the barrier alone).

   ``--barriers count:2,flag:2`` compares that barrier (spinning on the arrival counter) with
   one whose last arrival raises a release flag in a separate allocation that the others spin
   on, at 2 blocks per SM: on the H100 the flag was slower (2.3 against 2.0 us a phase at 16^2,
   3.0 against 2.7 at 256^2; taichi_grid_barrier_flag_H100.json), so the library keeps the
   counter.

Usage:  python perf/taichi_grid_barrier.py [--size 1024] [--frames 20] [--barriers count:1]
            [--skip-launch] [--out FILE]
Writes perf/results/taichi_grid_barrier_cuda0.json (the committed H100 runs: taichi_grid_barrier_cuda0_H100.json,
part 1 and the counter barrier at 1 block per SM; taichi_grid_barrier_flag_H100.json).
"""

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))
sys.path.insert(0, str(ROOT / "perf"))

from _fused_variants import profiling_kernels  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--block", type=int, default=256)
    ap.add_argument("--barriers", default="count:1",
                    help="barrier variants <kind>:<blocks per SM>, kind 'count' (spin on the arrival "
                         "counter) or 'flag' (the last arrival sets a release flag that the others spin on)")
    ap.add_argument("--skip-launch", action="store_true", help="only part 2 (the barriers)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)

    import torch

    from gpps import _taichi
    from gpps.camera import Orthographic
    from gpps.pipeline.integration_device import StreamIntegrator

    ti = _taichi.init("cuda:0")
    n = a.size
    sms = torch.cuda.get_device_properties(0).multi_processor_count
    res = {"device_name": torch.cuda.get_device_name(0), "sms": sms, "size": n, "frames": a.frames}

    def queued(fn, frames=a.frames, sleep_ms=30.0):
        """(host us per launch while the device sleeps, device us per launch)."""
        fn()
        torch.cuda.synchronize()
        hs, ds = [], []
        for _ in range(7):
            e0, e1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            torch.cuda._sleep(int(sleep_ms * 1.5e6))
            e0.record()
            t0 = time.perf_counter()
            for _ in range(frames):
                fn()
            t1 = time.perf_counter()
            e1.record()
            torch.cuda.synchronize()
            hs.append(1e6 * (t1 - t0) / frames)
            ds.append(1e3 * e0.elapsed_time(e1) / frames)
        return statistics.median(hs), statistics.median(ds)

    nrm = torch.zeros((n, n, 3), dtype=torch.float32, device="cuda")
    nrm[..., 2] = 1
    out = torch.zeros((n, n), dtype=torch.float32, device="cuda")
    si = StreamIntegrator(np.ones((n, n), bool), Orthographic(1.0 / n), device="cuda:0")
    K = {**si._K, **profiling_kernels(si._K)}  # with vcycle_only, noop
    frame = K["frame"](1)
    fld = si._F["sc"]

    @ti.kernel
    def noop_scalar(x: ti.f64):
        for i in range(1):
            fld[6] += x * 0

    @ti.kernel
    def noop_nd(x: ti.types.ndarray(), y: ti.types.ndarray()):
        for i in range(1):
            fld[6] += 0

    probes = {
        "noop_fields": K["noop"],
        "noop_one_scalar_arg": lambda: noop_scalar(0.0),
        "noop_two_torch_ndarrays": lambda: noop_nd(nrm, out),
        "vcycle_fields": K["vcycle_only"],
        "frame1_torch_args": lambda: frame(nrm, out, *si._cam, si.config.min_nz, 0.0),
        "integrate_1": lambda: si.step(nrm, out, iterations=1),
    }
    res["queued"] = {}
    for k, fn in ({} if a.skip_launch else probes).items():
        h, d = queued(fn)
        res["queued"][k] = {"host_us": h, "device_us": d}
        print(f"{k:28s} host {h:8.1f} us  device {d:8.1f} us", flush=True)
    si.close()

    # ---- grid barrier in one task
    BD = a.block
    LIMIT = 1 << 22
    bar = ti.field(ti.i32, shape=2)
    flag = ti.field(ti.i32, shape=1)  # a separate allocation: spinning does not contend with arrivals

    def build(h, w, kind, G):
        NT = G * BD
        x = ti.field(ti.f32, shape=(h, w))
        y = ti.field(ti.f32, shape=(h, w))
        per = (h * w + NT - 1) // NT

        @ti.func
        def avg5(src: ti.template(), i, j):
            s = src[i, j]
            if i > 0:
                s += src[i - 1, j]
            if i < h - 1:
                s += src[i + 1, j]
            if j > 0:
                s += src[i, j - 1]
            if j < w - 1:
                s += src[i, j + 1]
            return 0.2 * s

        @ti.func
        def stencil(src: ti.template(), dst: ti.template(), tid):
            for kk in range(per):
                c = tid + kk * NT
                if c < h * w:
                    dst[c // w, c % w] = avg5(src, c // w, c % w)

        @ti.func
        def gsync(tid, gen):
            ti.simt.grid.memfence()
            ti.simt.block.sync()
            if tid % BD == 0:
                old = ti.atomic_add(bar[0], 1)
                target = gen * G
                if ti.static(kind == "flag"):
                    if old == target - 1:
                        ti.atomic_max(flag[0], gen)
                k = 0
                while True:
                    v = 0
                    if ti.static(kind == "flag"):
                        v = ti.atomic_or(flag[0], 0) * G
                    else:
                        v = ti.atomic_or(bar[0], 0)
                    if v >= target:
                        break
                    k += 1
                    if k >= LIMIT:
                        bar[1] = 1
                    if k % 1024 == 0:
                        if ti.atomic_or(bar[1], 0) != 0:
                            break
            ti.simt.block.sync()
            ti.simt.grid.memfence()

        @ti.kernel
        def run(phases: ti.i32):
            bar[0] = 0
            flag[0] = 0
            ti.loop_config(block_dim=BD, block_dim_adaptive=False)
            for tid in range(NT):
                for p in range(phases):
                    if p % 2 == 0:
                        stencil(x, y, tid)
                    else:
                        stencil(y, x, tid)
                    gsync(tid, p + 1)

        @ti.kernel
        def sweep(src: ti.template(), dst: ti.template()):
            for i, j in ti.ndrange(h, w):
                dst[i, j] = avg5(src, i, j)

        return x, y, run, sweep

    def ref(x0, phases):
        u = x0.astype(np.float64)
        for _ in range(phases):
            p = np.pad(u, 1)
            u = 0.2 * (u + p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:])
        return u

    rng = np.random.default_rng(0)
    res["barrier"] = []
    for variant in a.barriers.split(","):
        kind, bps = variant.split(":")
        for (h, w) in ((n, n), (37, 29), (16, 16), (256, 256)):
            x, y, run, sweep = build(h, w, kind, sms * int(bps))
            x0 = rng.random((h, w)).astype(np.float32)
            errs = []
            for phases in (1, 2, 7, 40):
                x.from_numpy(x0)
                y.fill(0)
                bar.fill(0)
                run(phases)
                got = (y if phases % 2 else x).to_numpy()
                errs.append(float(np.abs(got - ref(x0, phases)).max()))
            timeout = int(bar.to_numpy()[1])
            P = 20 if h * w > 4096 else 200

            def launch():
                run(P)

            hst, dev = queued(launch, frames=5)

            def seq():
                for p in range(P):
                    if p % 2 == 0:
                        sweep(x, y)
                    else:
                        sweep(y, x)

            hs2, dv2 = queued(seq, frames=2)
            row = {"barrier": kind, "blocks_per_sm": int(bps), "shape": [h, w], "max_abs_error_vs_numpy": errs,
                   "timeout_flag": timeout, "phases": P,
                   "one_task_device_us_per_phase": dev / P, "one_task_host_us_per_launch": hst,
                   "separate_kernels_device_us_per_sweep": dv2 / P, "separate_kernels_host_us_per_sweep": hs2 / P}
            res["barrier"].append(row)
            print(row, flush=True)

    from gpps.io import save_json

    path = Path(a.out) if a.out else ROOT / "perf" / "results" / "taichi_grid_barrier_cuda0.json"
    save_json(path, res)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

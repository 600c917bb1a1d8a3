"""Stream soak: 10,000 frames with 1 % bad frames of every kind, against a clean stream in lockstep.

The scene: Blinn-Phong bumps, perspective, 3 directional lights, uint16 RGB
frames moving sideways (8 positions, one step every 2 frames).  The dirty
stream gets every frame; 1 % of them (at random positions, fixed seed) are bad,
the kinds in turn: NaN, wrong shape, wrong dtype, black, noise (RGB and grey),
saturated, negative.  A clean stream (same configuration) gets only the good
frames.  Measured:

* every bad frame reported (an error result naming the cause), no good frame
  rejected;
* every good frame of the dirty stream against the same frame of the clean
  stream: the largest angle over the mask (a small Warp kernel, read back one
  float a frame), which must stay below 1e-3 deg;
* the dirty stream's MAEN against the ground truth;
* memory: resident set size (/proc/self/statm) and, on CUDA, device memory in
  use, sampled every ``--every`` frames after a warm-up of 2,500 frames (Python
  fills its free lists in the first ~2,000); the growth from the first sample
  to the last;
* frames per second of the dirty stream (both streams run in one process, so
  this is half the wall rate).

On CUDA the frames are uploaded once (device-resident Warp arrays).

Usage:  python perf/stream_soak.py [--device cpu] [--size 64] [--frames 10000] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np  # noqa: E402

KINDS = ["nan", "shape", "dtype", "black", "noise", "grey-noise", "saturated", "negative"]
EXPECT = {"nan": "NaN", "shape": "shape", "dtype": "dtype", "black": "lit", "noise": "noise",
          "grey-noise": "noise", "saturated": "saturated", "negative": ">= 0"}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--frames", type=int, default=10000)
    ap.add_argument("--bad-share", type=float, default=0.01)
    ap.add_argument("--every", type=int, default=500)
    ap.add_argument("--warmup", type=int, default=2500)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()

    import _soak_kernels as sk
    from _common import moving_bumps, rss_mb

    from gpps._runtime import resolve_device, warp
    from gpps.pipeline.stream import Stream, StreamConfig

    wp = warp()
    dev = resolve_device(a.device)
    cuda = dev.startswith("cuda")
    npos = 8
    sc, mat, L, frames, truth, mask = moving_bumps(a.size, dev, npos)
    rng = np.random.default_rng(0)
    f0 = frames[0].astype(np.float32) / 65535
    bad = {
        "nan": np.where(np.arange(f0.size).reshape(f0.shape) == 7, np.nan, f0).astype(np.float32),
        "shape": frames[0][:, :-1].copy(),
        "dtype": frames[0].astype(np.int64),
        "black": np.zeros_like(frames[0]),
        "noise": rng.integers(0, 65536, frames[0].shape).astype(np.uint16),
        "grey-noise": rng.integers(0, 65536, frames[0].shape[:3]).astype(np.uint16),
        "saturated": np.full_like(frames[0], 65535),
        "negative": f0 - 0.5,
    }
    if cuda:  # device-resident frames: the stream copies on the device (the int64 one stays on the host)
        frames = [wp.array(f, dtype=wp.uint16, device=dev) for f in frames]
        for k, v in bad.items():
            if v.dtype in (np.uint16, np.float32):
                bad[k] = wp.array(v, dtype=wp.uint16 if v.dtype == np.uint16 else wp.float32, device=dev)
    nbad = int(round(a.bad_share * a.frames))
    where = np.sort(rng.choice(np.arange(10, a.frames), size=nbad, replace=False))
    plan = {int(i): KINDS[k % len(KINDS)] for k, i in enumerate(where)}

    cfg = StreamConfig(output="device", ring=2)
    clean = Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=cfg, device=dev)
    dirty = Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=cfg, device=dev)
    mdev = wp.array(mask.astype(np.uint8), dtype=wp.uint8, device=dev)
    worst = wp.zeros(1, dtype=wp.float32, device=dev)

    reported = {k: 0 for k in KINDS}
    misreported, rejected_good, max_dev, samples = [], [], 0.0, []
    maen_sum, maen_n, redone = 0.0, 0, 0
    good_i = 0
    t_dirty = 0.0
    t0 = time.perf_counter()
    for i in range(a.frames):
        kind = plan.get(i)
        if kind is not None:
            t = time.perf_counter()
            r = dirty.run(bad[kind])
            t_dirty += time.perf_counter() - t
            if r.ok or EXPECT[kind] not in (r.error or ""):
                misreported.append({"index": i, "kind": kind, "error": r.error})
            else:
                reported[kind] += 1
            continue
        pos = (good_i // 2) % npos
        good_i += 1
        t = time.perf_counter()
        rd = dirty.run(frames[pos])
        t_dirty += time.perf_counter() - t
        rc = clean.run(frames[pos])
        if not (rd.ok and rc.ok):
            rejected_good.append({"index": i, "dirty": rd.error, "clean": rc.error})
            continue
        redone += (rd.checks or {}).get("redone", 0)
        worst.zero_()
        wp.launch(sk.max_angle, dim=mask.shape, inputs=[rd.normals, rc.normals, mdev, worst], device=dev)
        max_dev = max(max_dev, float(worst.numpy()[0]))
        if i % 50 == 0:  # MAEN against the truth, every 50th good frame
            n = rd.normals.numpy()
            cosang = np.clip((n * truth[pos]).sum(-1), -1, 1)[mask]
            maen_sum += float(np.degrees(np.arccos(cosang)).mean())
            maen_n += 1
        if i + 1 >= a.warmup and ((i + 1) % a.every == 0 or i + 1 == a.frames):
            wp.synchronize_device(dev)
            d = wp.get_device(dev)
            samples.append({"frame": i + 1, "rss_mb": rss_mb(),
                            "device_used_mb": (d.total_memory - d.free_memory) / 2**20 if cuda else None})
            print(f"frame {i + 1:6d}  rss {samples[-1]['rss_mb']:8.1f} MB  device {samples[-1]['device_used_mb']}  "
                  f"max dev {max_dev:.2e} deg  reported {sum(reported.values())}", file=sys.stderr, flush=True)
    wall = time.perf_counter() - t0
    first, last = samples[0], samples[-1]
    res = {
        "device": dev, "device_name": wp.get_device(dev).name, "size": a.size, "frames": a.frames,
        "bad_frames_planned": {k: sum(1 for v in plan.values() if v == k) for k in KINDS},
        "bad_frames_reported": reported, "misreported": misreported, "good_frames_rejected": rejected_good,
        "good_frames": good_i, "max_deviation_from_clean_deg": max_dev,
        "maen_deg_dirty_stream": maen_sum / max(maen_n, 1), "pixels_redone_cold": int(redone),
        "wall_s": wall, "dirty_stream_s": t_dirty, "dirty_frames_per_s": a.frames / t_dirty,
        "rss_growth_mb": last["rss_mb"] - first["rss_mb"],
        "device_growth_mb": None if first["device_used_mb"] is None else last["device_used_mb"] - first["device_used_mb"],
        "samples": samples, "command": "python perf/stream_soak.py " + " ".join(sys.argv[1:]),
    }
    out = Path(a.out or ROOT / "perf" / "results" / f"stream_soak_{dev.replace(':', '')}_{a.size}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(res, indent=1, default=float))
    os.replace(tmp, out)
    ok = not misreported and not rejected_good and max_dev < 1e-3
    print(f"{a.frames} frames at {a.size}^2 on {res['device_name']}: {sum(reported.values())}/{nbad} bad frames "
          f"reported ({len(misreported)} missed or misnamed), {len(rejected_good)} good frames rejected, "
          f"max deviation from the clean stream {max_dev:.2e} deg, MAEN {res['maen_deg_dirty_stream']:.3f} deg, "
          f"{res['dirty_frames_per_s']:.0f} frames/s, RSS growth {res['rss_growth_mb']:+.2f} MB, device growth "
          f"{res['device_growth_mb']} MB -> {out}  [{'PASS' if ok else 'FAIL'}]")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""The stream's full mode (material unknown) on a moving scene: triples/s device-resident and MAEN per frame beside
the offline ``gpps.reconstruct`` of the same frames, known mode beside it (issue 20's Done-when line).

Scene: bumps, perspective, 3 directional lights, RGB 16-bit frames rendered with Cook-Torrance (ks 0.8, m 0.2,
f0 0.5), the object moved one pixel a frame back and forth over ``--positions`` positions
(:func:`_common.moving_bumps`).  The frames are uploaded to the device once (uint16 Warp arrays) and fed to the
stream from there: the figure is the device-resident rate.

* full mode: ``StreamConfig(material="estimate")`` from a wrong guess (ks 0.3, m 0.5).  Its frames fall into
  the start (the first, cold frame with the grid of the material search and DGMC; the search's frames, one
  batch of candidates each, with the rolling cold re-solve after each material change) and the steady state
  (search settled, one refinement batch every ``refine_every`` frames).  Reported: the first frame's seconds,
  the start's frames and median, and over the steady state (the last ``--timed`` frames): triples/s as frames /
  wall time (every frame is device-synchronised by the stream's own read-back; refinement frames included) and
  the median frame time.
* known mode: the same frames with the true material, timed the same way.
* offline: ``gpps.reconstruct(..., material="cook-torrance")`` (ks and roughness estimated) on ``--offline``
  positions; MAEN of each, and the stream's MAEN on the frames at those positions in the steady state.

Writes perf/results/stream_full_<device>.json.

Usage:  python perf/stream_full.py [--size 1024] [--frames 160] [--timed 80] [--device cuda:0]
        python perf/stream_full.py --size 64 --frames 60 --timed 24 --device cpu     (a check on the CPU)
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np  # noqa: E402
from _common import moving_bumps, write_results  # noqa: E402

import gpps  # noqa: E402
from gpps._runtime import resolve_device, warp  # noqa: E402
from gpps.host.metrics import normal_errors  # noqa: E402
from gpps.material import Material  # noqa: E402
from gpps.pipeline.stream import Stream, StreamConfig  # noqa: E402

TRUE = Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)
GUESS = Material("cook-torrance", ks=0.3, roughness=0.5, f0=0.5)


def run_stream(frames_dev, seq, truth, mask, sc, L, material, cfg, device):
    """Run the stream over ``seq``; returns per-frame seconds (device-synchronised), MAEN, estimates, stats."""
    wp = warp()
    st = Stream(mask.shape, sc.camera, L, material, mask=mask, config=cfg, device=device)
    secs, maen, mats, scored, settled = [], [], [], [], []
    for p in seq:
        before = st.stats.get("material_batches", 0)
        t0 = time.perf_counter()
        r = st.run(frames_dev[p])
        wp.synchronize_device(device)
        secs.append(time.perf_counter() - t0)
        scored.append(st.stats.get("material_batches", 0) > before)
        settled.append(st.estimator is not None and st.estimator.settled)
        if not r.ok:
            maen.append(float("nan"))
        else:
            maen.append(normal_errors(r.normals.numpy(), truth[p], mask)["mean"])  # outside the timed region
        mats.append({"ks": r.material.ks, "roughness": r.material.roughness} if r.material is not None else None)
    return st, secs, maen, mats, scored, settled


def summary(secs, timed):
    tail = secs[-timed:]
    return {"first_frame_s": secs[0], "steady_frames": len(tail), "steady_triples_per_s": len(tail) / sum(tail),
            "steady_median_s": statistics.median(tail), "steady_max_s": max(tail)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--positions", type=int, default=8)
    ap.add_argument("--frames", type=int, default=160)
    ap.add_argument("--timed", type=int, default=80, help="the last frames: the steady state that is timed")
    ap.add_argument("--offline", type=int, nargs="*", default=[0, 4],
                    help="positions reconstructed offline (material unknown)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE",
                    help="StreamConfig fields for both modes (an ablation), e.g. material_tol=0.01")
    a = ap.parse_args(argv)
    over, base = {}, StreamConfig()
    for kv in a.set:
        k, _, v = kv.partition("=")
        if not hasattr(base, k):
            ap.error(f"--set: StreamConfig has no field {k!r}")
        old = getattr(base, k)
        if isinstance(old, bool):
            over[k] = v.lower() in ("1", "true", "yes")
        else:
            over[k] = int(v) if old is None else type(old)(v)
    wp = warp()
    device = resolve_device(a.device)
    log = lambda s: print(s, flush=True)  # noqa: E731
    t0 = time.perf_counter()
    sc, _, L, fr, truth, mask = moving_bumps(a.size, device, a.positions, material=TRUE)
    frames_dev = [wp.array(f, dtype=wp.uint16, device=device) for f in fr]
    path = list(range(a.positions)) + list(range(a.positions - 2, 0, -1))
    seq = [path[i % len(path)] for i in range(a.frames)]
    log(f"[{a.size}] scene: {a.positions} positions, {a.frames} frames, rendered in {time.perf_counter() - t0:.1f}s")

    rows = {}
    full = StreamConfig(output="device", material="estimate", **over)
    st, secs, maen, mats, scored, settled = run_stream(frames_dev, seq, truth, mask, sc, L, GUESS, full, device)
    settled_at = next((i for i, v in enumerate(settled) if v), None)  # the first frame after which it had settled
    rows["full"] = {**summary(secs, a.timed), "seconds_per_frame": secs, "maen_per_frame": maen,
                    "material_per_frame": mats, "scored_per_frame": scored, "stats": dict(st.stats),
                    "start_frames": settled_at, "estimate": mats[-1],
                    "start_median_s": statistics.median(secs[1:settled_at]) if settled_at and settled_at > 1 else None}
    log(f"[{a.size}] full:  first frame {secs[0]:.3f}s, search start {settled_at} frames, steady "
        f"{rows['full']['steady_triples_per_s']:.1f} triples/s (median {1e3 * rows['full']['steady_median_s']:.2f} ms), "
        f"estimate {mats[-1]}, stats {st.stats}")
    known = StreamConfig(output="device", **over)
    st, secs, maen_k, _, _, _ = run_stream(frames_dev, seq, truth, mask, sc, L, TRUE, known, device)
    rows["known"] = {**summary(secs, a.timed), "seconds_per_frame": secs, "maen_per_frame": maen_k}
    log(f"[{a.size}] known: first frame {secs[0]:.3f}s, steady {rows['known']['steady_triples_per_s']:.1f} triples/s "
        f"(median {1e3 * rows['known']['steady_median_s']:.2f} ms)")

    unit = gpps.DirectionalLights(L.directions)
    inten = np.asarray(L.intensities, np.float32)[:, None, None, :]
    off = {}
    for p in a.offline:
        img = fr[p].astype(np.float32) / 65535 / inten  # what the stream's conversion gives its solver
        t = time.perf_counter()
        rec = gpps.reconstruct(img, mask, unit, camera=sc.camera, material="cook-torrance", device=device)
        dt = time.perf_counter() - t
        steady = [maen[i] for i in range(len(seq) - a.timed, len(seq)) if seq[i] == p]
        steady_k = [maen_k[i] for i in range(len(seq) - a.timed, len(seq)) if seq[i] == p]
        off[p] = {"maen_offline": normal_errors(rec.normals, truth[p], mask)["mean"], "estimated": rec.estimated,
                  "seconds": dt, "maen_stream_full": float(np.nanmean(steady)) if steady else None,
                  "maen_stream_known": float(np.nanmean(steady_k)) if steady_k else None}
        log(f"[{a.size}] offline position {p}: MAEN {off[p]['maen_offline']:.3f} deg ({dt:.1f}s, {rec.estimated}); "
            f"stream full {off[p]['maen_stream_full']}, known {off[p]['maen_stream_known']}")
    both = [v for v in off.values() if v["maen_stream_full"] is not None]
    ratio = (float(np.mean([v["maen_stream_full"] for v in both])) / float(np.mean([v["maen_offline"] for v in both]))
             if both else None)
    tail = slice(len(seq) - a.timed, len(seq))
    log(f"[{a.size}] MAEN steady mean: full {np.nanmean(maen[tail]):.3f}, known {np.nanmean(maen_k[tail]):.3f}; "
        f"full / offline at the offline positions: {ratio}")
    path_out = write_results("stream_full", device, {
        "size": a.size, "positions": a.positions, "frames": a.frames, "timed": a.timed, "position_per_frame": seq,
        "scene": "bumps, perspective, 3 directional lights, RGB uint16, Cook-Torrance ks 0.8 m 0.2 f0 0.5; "
                 "full mode from ks 0.3 m 0.5", "full": rows["full"], "known": rows["known"],
        "offline": {str(k): v for k, v in off.items()}, "config_set": over, "maen_full_over_offline": ratio,
        "maen_steady_full": float(np.nanmean(maen[tail])), "maen_steady_known": float(np.nanmean(maen_k[tail])),
        "command": "python perf/stream_full.py " + " ".join(argv if argv is not None else sys.argv[1:]),
    })
    log(f"wrote {path_out}")


if __name__ == "__main__":
    main()

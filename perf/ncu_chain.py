"""Nsight Compute counters of the offline chain's kernels: the reason beside each ratio of ``bench.py --chain``.

Runs ``perf/bench.py --ncu-driver K`` (every chain kernel set up as the bench sets it up, then launched K
times outside CUDA graphs inside one CUDA profiler range) under ``ncu --profile-from-start off``, exports
the report, reads it back with ``ncu --import ... --csv --page raw`` and writes
``perf/results/ncu_chain_<gpu>.json``: per kernel launch its name, block and grid size, registers per
thread and the counters of :data:`METRICS` (achieved and theoretical occupancy, issue-slot utilisation,
the FMA / FP64 / ALU / XU (special-function) / LSU pipes, DRAM / L2 / L1 throughput, active threads per
warp instruction, duration), and per chain row (``dgmc_highlight``, ``scorer_solve_96img``, ...) the
median of its launches beside the bench's ratio when ``perf/results/bench_chain_<gpu>.json`` exists.

Launches are matched to rows by order: the driver writes the order (a manifest) and each row's name
pattern.  Taichi (BiNI's CG) may run in a CUDA context of its own, which the Warp-side profiler range
does not cover; then a second ncu pass profiles the first CG tasks of a BiNI-only driver by name.
ncu locks the clocks to base by default: its durations are not the bench's (the percentages are what
this script is for).  A metric this ncu or GPU does not know is dropped (and listed) and the run retried.

Without ``ncu`` (on PATH, /usr/local/cuda*/bin, /opt/nvidia/nsight-compute/*/) it writes a JSON that says so
and exits 0; when ncu fails (e.g. ERR_NVGPUCTRPERM: no access to the performance counters) the JSON holds
the reason and the exit status is 1.

Usage:  python perf/ncu_chain.py [--device cuda:0] [--launches 2] [--chain-size 166 --chain-images 96
        --chain-samples 2000 --chain-candidates 25] [--ncu PATH] [--timeout 900] [--out FILE]
"""

from __future__ import annotations

import argparse
import csv
import glob
import io
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
import _bench_chain  # noqa: E402  (its PARTS: numpy only at import)
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))
BENCH = ROOT / "perf" / "bench.py"
RESULTS = ROOT / "perf" / "results"

# our name -> ncu metric
METRICS = {
    "duration_ns": "gpu__time_duration.sum",
    "achieved_occupancy_pct": "sm__warps_active.avg.pct_of_peak_sustained_active",
    "theoretical_occupancy_pct": "sm__maximum_warps_per_active_cycle_pct",
    "issue_slots_pct": "sm__inst_issued.avg.pct_of_peak_sustained_active",
    "fma_pipe_pct": "sm__inst_executed_pipe_fma.avg.pct_of_peak_sustained_active",
    "fp64_pipe_pct": "sm__inst_executed_pipe_fp64.avg.pct_of_peak_sustained_active",
    "alu_pipe_pct": "sm__inst_executed_pipe_alu.avg.pct_of_peak_sustained_active",
    "xu_pipe_pct": "sm__inst_executed_pipe_xu.avg.pct_of_peak_sustained_active",
    "lsu_pipe_pct": "sm__inst_executed_pipe_lsu.avg.pct_of_peak_sustained_active",
    "sm_throughput_pct": "sm__throughput.avg.pct_of_peak_sustained_elapsed",
    "dram_throughput_pct": "dram__throughput.avg.pct_of_peak_sustained_elapsed",
    "l2_throughput_pct": "lts__throughput.avg.pct_of_peak_sustained_elapsed",
    "l1_throughput_pct": "l1tex__throughput.avg.pct_of_peak_sustained_active",
    "threads_per_warp_inst": "smsp__thread_inst_executed_per_inst_executed.ratio",
    "registers_per_thread": "launch__registers_per_thread",
    "block_size": "launch__block_size",
    "grid_size": "launch__grid_size",
    "waves_per_sm": "launch__waves_per_multiprocessor",
}
TABLE = [("dur_us", "duration_ns", 1e-3), ("occ", "achieved_occupancy_pct", 1), ("theo", "theoretical_occupancy_pct", 1),
         ("issue", "issue_slots_pct", 1), ("fma", "fma_pipe_pct", 1), ("fp64", "fp64_pipe_pct", 1),
         ("alu", "alu_pipe_pct", 1), ("xu", "xu_pipe_pct", 1), ("dram", "dram_throughput_pct", 1),
         ("l2", "l2_throughput_pct", 1), ("thr/w", "threads_per_warp_inst", 1), ("regs", "registers_per_thread", 1),
         ("block", "block_size", 1), ("grid", "grid_size", 1)]


def log(s: str) -> None:
    print(s, file=sys.stderr, flush=True)


def find_ncu(explicit: str | None) -> str | None:
    """The Nsight Compute CLI: ``explicit``, on PATH, under /usr/local/cuda*/bin or /opt/nvidia/nsight-compute."""
    cands = [explicit] if explicit else []
    cands += [shutil.which("ncu"), "/usr/local/cuda/bin/ncu"]
    cands += sorted(glob.glob("/opt/nvidia/nsight-compute/*/ncu"), reverse=True)
    cands += sorted(glob.glob("/usr/local/cuda-*/bin/ncu"), reverse=True)
    for c in cands:
        if c and os.path.isfile(c) and os.access(c, os.X_OK):
            return c
    return None


def run_logged(cmd, timeout: float) -> tuple[int, str]:
    """Run ``cmd`` from the repository root, its output echoed to stderr as it comes; (status, output)."""
    log("$ " + " ".join(cmd))
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            errors="replace")
    killed = []
    timer = threading.Timer(timeout, lambda: (killed.append(1), proc.kill()))
    timer.start()
    lines = []
    try:
        for line in proc.stdout:
            lines.append(line)
            sys.stderr.write("  | " + line)
        rc = proc.wait()
    finally:
        timer.cancel()
    if killed:
        lines.append(f"\n(killed after the {timeout:.0f} s timeout)\n")
    return rc, "".join(lines)


def profile(ncu, rep, metrics: dict, driver_args, extra, timeout) -> tuple[dict, list, str]:
    """ncu over the driver; drops metrics ncu does not know and retries.  (metrics used, dropped, error or '')."""
    metrics = dict(metrics)
    dropped = []
    for _ in range(4):
        cmd = [ncu, "--export", rep, "--force-overwrite", "--target-processes", "all", *extra,
               "--metrics", ",".join(metrics.values()), sys.executable, str(BENCH), *driver_args]
        rc, out = run_logged(cmd, timeout)
        if "ERR_NVGPUCTRPERM" in out:
            return metrics, dropped, ("ERR_NVGPUCTRPERM: no access to the GPU performance counters (run as root, or "
                                      "load the driver with NVreg_RestrictProfilingToAdminUsers=0)")
        bad = [k for k, m in metrics.items() if any(m in ln and "ERROR" in ln.upper() for ln in out.splitlines())]
        if bad and rc != 0:
            log(f"ncu does not know {[metrics[k] for k in bad]}: dropped, retrying")
            dropped += [metrics.pop(k) for k in bad]
            continue
        if rc != 0 or not os.path.exists(rep + ".ncu-rep"):
            tail = "".join(out.splitlines(keepends=True)[-30:])
            return metrics, dropped, f"ncu exited with {rc}; last output:\n{tail}"
        return metrics, dropped, ""
    return metrics, dropped, "ncu kept failing on unknown metrics"


def read_report(ncu, rep) -> list[dict]:
    """The report's raw page: one dict per profiled kernel launch, values as numbers where they are."""
    for units in (["--print-units", "base"], []):
        p = subprocess.run([ncu, "--import", rep + ".ncu-rep", "--csv", "--page", "raw", *units], cwd=ROOT,
                           capture_output=True, text=True, errors="replace", check=False)
        if p.returncode == 0:
            break
    else:
        raise RuntimeError(f"ncu --import failed: {p.stderr[-2000:]}")
    return parse_raw_csv(p.stdout)


def parse_raw_csv(text: str) -> list[dict]:
    """``ncu --csv --page raw`` output (a header, a units row, a row per launch; ``==PROF==`` lines skipped):
    one dict per launch in ``ID`` order, numbers (thousands separators removed) as floats."""
    text = "\n".join(ln for ln in text.splitlines() if not ln.startswith("=="))
    rows = list(csv.reader(io.StringIO(text)))
    if len(rows) < 2:
        return []
    head, body = rows[0], rows[2:]  # rows[1]: the units
    out = []
    for r in body:
        if len(r) != len(head):
            continue
        d = {}
        for k, v in zip(head, r):
            try:
                d[k] = float(v.replace(",", ""))
            except ValueError:
                d[k] = v
        out.append(d)
    out.sort(key=lambda d: d.get("ID", 0) if isinstance(d.get("ID"), float) else 0)
    return out


def assign(kernels: list[dict], manifest: list[dict]) -> tuple[dict, list]:
    """Match profiled launches (in launch order) to the manifest's rows, in the manifest's order.

    From where the previous row ended, a row takes the next ``kernels`` launches whose name matches its
    pattern (``kernels`` None: the first match and every match right after it); launches it skips stay
    free.  A row that matches nothing takes nothing and moves nothing on.  Returns ``(launches per row,
    the launches no row took)``.
    """
    by_label = {e["label"]: [] for e in manifest}
    used = set()
    pos = 0
    for e in manifest:
        pat = re.compile(e["pattern"])
        want = e.get("kernels")
        got = by_label[e["label"]]
        last = None
        for i in range(pos, len(kernels)):
            if want is not None and len(got) >= want:
                break
            if i in used:
                continue
            if pat.search(str(kernels[i].get("Kernel Name", ""))):
                got.append(kernels[i])
                used.add(i)
                last = i
            elif want is None and got:
                break  # the end of an open-ended run
        if last is not None:
            pos = last + 1
    return by_label, [k for i, k in enumerate(kernels) if i not in used]


def summarise(launches: list[dict], metrics: dict) -> dict:
    """Per kernel name: the median of each metric over its launches (our names), and the launch count."""
    names = {}
    for k in launches:
        names.setdefault(str(k.get("Kernel Name", "?")), []).append(k)
    out = {}
    for name, ks in names.items():
        s = {"launches": len(ks)}
        for ours, m in metrics.items():
            vals = [k[m] for k in ks if isinstance(k.get(m), float)]
            if vals:
                s[ours] = statistics.median(vals)
        out[name] = s
    return out


def short(name: str, width: int = 34) -> str:
    name = re.sub(r"_[0-9a-f]{6,}_cuda_kernel_forward$", "", name)
    return name if len(name) <= width else name[: width - 1] + "~"


def print_table(summary: dict, ratios: dict) -> None:
    print(f"\n{'row':24s} {'kernel':34s} {'ratio':>6s} " + " ".join(f"{h:>7s}" for h, _, _ in TABLE))
    for label, per in summary.items():
        if not per:
            print(f"{label:24s} {'(no launch profiled)':34s}")
        for name, s in per.items():
            vals = []
            for _, ours, scale in TABLE:
                v = s.get(ours)
                vals.append(f"{v * scale:7.1f}" if isinstance(v, float) else f"{'-':>7s}")
            r = ratios.get(label)
            print(f"{label:24s} {short(name):34s} {r if r is None else round(r, 2)!s:>6s} " + " ".join(vals))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--launches", type=int, default=2, help="launches of each kernel profiled")
    ap.add_argument("--chain-size", type=int, default=None)
    ap.add_argument("--chain-images", type=int, default=None)
    ap.add_argument("--chain-samples", type=int, default=None)
    ap.add_argument("--chain-candidates", type=int, default=None)
    ap.add_argument("--chain-parts", nargs="*", default=None)
    ap.add_argument("--ncu", default=None, help="path of ncu (default: searched)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds for each ncu run")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    ncu = find_ncu(a.ncu)
    from _common import device_label

    try:
        label = device_label(a.device)
    except Exception as e:  # noqa: BLE001 - no CUDA here: still say what happened
        label = device_label("cpu")
        log(f"device {a.device!r} unavailable ({e!r}); labelling the result {label}")
    path = Path(a.out) if a.out else RESULTS / f"ncu_chain_{label}.json"
    base = {"device": a.device, "device_name": label, "command": "python perf/ncu_chain.py " + " ".join(
        sys.argv[1:] if argv is None else argv), "metrics": METRICS}
    if ncu is None:
        base.update(ncu=None, status="skipped", reason="ncu (Nsight Compute CLI) not found on PATH, "
                    "/usr/local/cuda*/bin or /opt/nvidia/nsight-compute/*/")
        _write(path, base)
        log(f"ncu not found: nothing profiled; wrote {path}")
        return 0
    ver = subprocess.run([ncu, "--version"], capture_output=True, text=True, errors="replace",
                         check=False).stdout.strip()
    base.update(ncu=ncu, ncu_version=ver.splitlines()[-1] if ver else "")
    log(f"ncu: {ncu} ({base['ncu_version']})")
    if not a.device.startswith("cuda"):
        base.update(status="skipped", reason=f"device {a.device!r}: Nsight Compute profiles CUDA kernels only")
        _write(path, base)
        log(f"{base['reason']}; wrote {path}")
        return 0
    chain = []
    for opt in ("chain_size", "chain_images", "chain_samples", "chain_candidates"):
        if getattr(a, opt) is not None:
            chain += ["--" + opt.replace("_", "-"), str(getattr(a, opt))]
    with tempfile.TemporaryDirectory(prefix="ncu_chain_") as tmp:
        manifest_path = os.path.join(tmp, "manifest.json")
        driver = ["--device", a.device, "--ncu-driver", str(a.launches), "--out", manifest_path, *chain]
        if a.chain_parts:
            driver += ["--chain-parts", *a.chain_parts]
        rep = os.path.join(tmp, "chain")
        metrics, dropped, err = profile(ncu, rep, METRICS, driver, ["--profile-from-start", "off"], a.timeout)
        base.update(metrics={k: v for k, v in METRICS.items() if v in metrics.values()}, dropped_metrics=dropped)
        if err:
            base.update(status="failed", reason=err)
            _write(path, base)
            log(f"FAILED: {err}\nwrote {path}")
            return 1
        manifest = json.loads(Path(manifest_path).read_text())
        kernels = read_report(ncu, rep)
        log(f"{len(kernels)} kernel launches profiled")
        by_label, unassigned = assign(kernels, manifest["launches"])
        notes = []
        for e in manifest["launches"]:
            if e["taichi"] and not by_label[e["label"]]:
                # Taichi's context is outside the Warp-side range: profile its first CG tasks by name
                # (the part that registered the row: its label's prefix, bini_cg_iteration -> bini,
                # rounds_pcg_iteration -> rounds)
                part = e["label"].split("_")[0]
                part = part if part in _bench_chain.PARTS else "bini"
                log(f"{e['label']}: no launch in the profiler range (Taichi's own CUDA context?); "
                    f"a second pass profiles the first tasks of a {part}-only driver")
                rep2 = os.path.join(tmp, part)
                drv2 = ["--device", a.device, "--ncu-driver", "1", "--out", os.path.join(tmp, f"m2_{part}.json"),
                        *chain, "--chain-parts", part]
                _, _, err2 = profile(ncu, rep2, metrics, drv2, ["--kernel-name", "regex:" + e["pattern"],
                                                                 "--launch-count", str(12 * a.launches)], a.timeout)
                if err2:
                    notes.append(f"{e['label']}: second pass failed: {err2}")
                else:
                    by_label[e["label"]] = read_report(ncu, rep2)
                    notes.append(f"{e['label']}: from a second pass (profiled from the start, the first "
                                 f"{12 * a.launches} launches whose name matches {e['pattern']!r})")
    ratios = {}
    bench_json = RESULTS / f"bench_chain_{label}.json"
    if bench_json.exists():
        ratios = {r["kernel"]: r.get("ratio") for r in json.loads(bench_json.read_text()).get("rows", [])}
    metrics_used = base["metrics"]
    summary = {lab: summarise(ks, metrics_used) for lab, ks in by_label.items()}
    base.update(status="ok", chain=manifest, bench_ratios=ratios, summary=summary, notes=notes,
                launches={lab: ks for lab, ks in by_label.items()},
                unassigned=[str(k.get("Kernel Name", "?")) for k in unassigned],
                seconds=time.perf_counter() - t0)
    _write(path, base)
    print_table(summary, ratios)
    if unassigned:
        print(f"{len(unassigned)} profiled launch(es) matched no row: {sorted(set(base['unassigned']))[:8]}")
    for n in notes:
        print("note:", n)
    print(f"wrote {path} ({time.perf_counter() - t0:.0f} s)")
    return 0


def _write(path: Path, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2, default=str) + "\n")


if __name__ == "__main__":
    sys.exit(main())

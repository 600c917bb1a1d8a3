"""The chain's roofline table: ``perf/bench.py --chain``'s ratios beside ``perf/ncu_chain.py``'s counters, as Markdown.

One line per (row, kernel): the bench's ratio (measured time over the hand-counted roofline time), the kernel's
registers, theoretical and achieved occupancy, issue-slot use, the FMA, FP64 and XU (special-function) pipes,
DRAM throughput, active threads per warp instruction and its duration under ncu (base clocks).  A row's Taichi
tasks (one per top-level loop) are summed into one line: their total duration, the range of their occupancies.
A ``why`` column is left for the reading (``--why FILE``: a JSON ``{row: text}`` fills it).

Usage:  python perf/chain_roofline.py BENCH_JSON NCU_JSON [--why FILE] [--out FILE.md]
"""

from __future__ import annotations

import argparse
import json
import re
import sys


def lines(bench: dict, ncu: dict, why: dict) -> list[str]:
    ratios = {r["kernel"]: r for r in bench.get("rows", [])}
    out = ["| row | bench ms | ratio | bound | kernel | launches | regs | occ. theo / achieved % | issue % | FMA % | "
           "FP64 % | XU % | DRAM % | thr/warp | ncu us | why (from the counters) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row, kernels in ncu.get("summary", {}).items():
        b = ratios.get(row, {})
        ratio = f"{b['ratio']:.1f}" if b.get("ratio") is not None else "-"
        ms = f"{b['seconds'] * 1e3:.3f}" if "seconds" in b else "-"
        bound = b.get("limited_by", "-")
        items = list(kernels.items())
        taichi = all(re.search(r"_c\d+_\d+_kernel_\d+_(range_for|serial)$", k) for k, _ in items)  # Taichi tasks
        if taichi:  # one line for the task list
            dur = sum(v.get("duration_ns", 0.0) for _, v in items) / 1e3
            par = [v for k, v in items if k.endswith("range_for")] or [v for _, v in items]  # (the parallel tasks)
            occ = [v.get("achieved_occupancy_pct", 0.0) for v in par]
            iss = [v.get("issue_slots_pct", 0.0) for v in par]
            dram = [v.get("dram_throughput_pct", 0.0) for _, v in items]
            name = items[0][0].rsplit("_kernel_", 1)[0] + f" ({len(items)} tasks)"
            out.append(f"| {row} | {ms} | {ratio} | {bound} | {name} | {items[0][1].get('launches', '')} | "
                       f"{min(v.get('registers_per_thread', 0) for _, v in items):.0f}-"
                       f"{max(v.get('registers_per_thread', 0) for _, v in items):.0f} | - / {min(occ):.1f}-{max(occ):.1f} | "
                       f"{min(iss):.1f}-{max(iss):.1f} | - | - | - | {max(dram):.1f} | - | {dur:.1f} | {why.get(row, '')} |")
            continue
        for k, v in items:
            def f(key, fmt="{:.1f}"):
                x = v.get(key)
                return "-" if x is None else fmt.format(x)
            out.append(f"| {row} | {ms} | {ratio} | {bound} | {k[:44]} | {v.get('launches', '')} | "
                       f"{f('registers_per_thread', '{:.0f}')} | {f('theoretical_occupancy_pct')} / "
                       f"{f('achieved_occupancy_pct')} | {f('issue_slots_pct')} | {f('fma_pipe_pct')} | "
                       f"{f('fp64_pipe_pct')} | {f('xu_pipe_pct')} | {f('dram_throughput_pct')} | "
                       f"{f('threads_per_warp_inst')} | {v.get('duration_ns', 0.0) / 1e3:.1f} | {why.get(row, '')} |")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench")
    ap.add_argument("ncu")
    ap.add_argument("--why", default=None, help="JSON {row: reason}")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    with open(a.bench) as fh:
        bench = json.load(fh)
    with open(a.ncu) as fh:
        ncu = json.load(fh)
    why = {}
    if a.why:
        with open(a.why) as fh:
            why = json.load(fh)
    text = "\n".join(lines(bench, ncu, why)) + "\n"
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

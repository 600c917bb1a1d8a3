"""perf/ncu_chain.py's host side: reading ncu's raw CSV, matching launches to the chain's rows, no ncu at all.

The profiling itself needs a GPU and Nsight Compute; what is tested here decides which counters land beside
which bench row, so a wrong match would put one kernel's reason beside another's ratio.
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "perf"))

import ncu_chain

RAW = """==PROF== Connected to process 4242 (/usr/bin/python3.12)
"ID","Process ID","Process Name","Host Name","Kernel Name","Context","Stream","Block Size","Grid Size","Device","CC","gpu__time_duration.sum","launch__registers_per_thread","sm__warps_active.avg.pct_of_peak_sustained_active"
"","","","","","","","","","","","nsecond","register/thread","%"
"1","4242","python3.12","127.0.0.1","geodesic_copy_kernel_0a1b2c3d_cuda_kernel_forward","1","7","(256, 1, 1)","(108, 1, 1)","0","9.0","3,104","32","61.5"
"0","4242","python3.12","127.0.0.1","geodesic_relax_kernel_0a1b2c3d_cuda_kernel_forward","1","7","(256, 1, 1)","(108, 1, 1)","0","9.0","1,234,567","128","12.25"
==PROF== Disconnected from process 4242
"""


def test_parse_raw_csv_orders_by_id_and_reads_numbers():
    rows = ncu_chain.parse_raw_csv(RAW)
    assert [r["ID"] for r in rows] == [0.0, 1.0]
    assert rows[0]["Kernel Name"].startswith("geodesic_relax_kernel")
    assert rows[0]["gpu__time_duration.sum"] == 1234567.0  # thousands separators removed
    assert rows[0]["launch__registers_per_thread"] == 128.0
    assert rows[1]["sm__warps_active.avg.pct_of_peak_sustained_active"] == 61.5
    assert rows[0]["Block Size"] == "(256, 1, 1)"  # not a number: kept as text
    assert ncu_chain.parse_raw_csv("==PROF== nothing profiled\n") == []


def _k(i, name):
    return {"ID": float(i), "Kernel Name": name}


def test_assign_by_order_counts_and_patterns():
    manifest = [
        {"label": "dgmc_highlight", "pattern": "highlight_kernel", "kernels": 2},
        {"label": "dgmc_geodesic_sweep", "pattern": "geodesic_(relax|copy)_kernel", "kernels": 4},
        {"label": "never_seen", "pattern": "no_such_kernel", "kernels": 2},
        {"label": "scorer_solve_96img", "pattern": "solve_batched_kernel", "kernels": 2},
        {"label": "scorer_solve_3img", "pattern": "solve_batched_kernel", "kernels": 2},
        {"label": "pixel_solve_96img", "pattern": "(solve|underdetermined)_kernel", "kernels": 4},
        {"label": "bini_cg_iteration", "pattern": "^cg", "kernels": None},
    ]
    names = (["highlight_kernel_aa_cuda_kernel_forward"] * 2
             + ["geodesic_relax_kernel_bb_cuda_kernel_forward", "geodesic_copy_kernel_bb_cuda_kernel_forward"] * 2
             + ["memset_stray"]
             + ["solve_batched_kernel__batched_lm_cc_cuda_kernel_forward"] * 4
             + ["solve_kernel__lm_dd_cuda_kernel_forward", "underdetermined_kernel__lm_dd_cuda_kernel_forward"] * 2
             + ["cg_c80_0_kernel_0_range_for", "cg_c80_0_kernel_1_range_for"] * 3)
    kernels = [_k(i, n) for i, n in enumerate(names)]
    by, unassigned = ncu_chain.assign(kernels, manifest)
    ids = {lab: [int(k["ID"]) for k in ks] for lab, ks in by.items()}
    assert ids["dgmc_highlight"] == [0, 1]
    assert ids["dgmc_geodesic_sweep"] == [2, 3, 4, 5]
    assert ids["never_seen"] == []
    assert ids["scorer_solve_96img"] == [7, 8]  # the first two batched launches ...
    assert ids["scorer_solve_3img"] == [9, 10]  # ... and the next two: order, not name, tells them apart
    assert ids["pixel_solve_96img"] == [11, 12, 13, 14]
    assert ids["bini_cg_iteration"] == list(range(15, 21))  # open-ended: every consecutive CG task
    assert [k["Kernel Name"] for k in unassigned] == ["memset_stray"]


def test_summarise_medians_per_kernel_name():
    ks = [{"Kernel Name": "a", "gpu__time_duration.sum": v, "launch__block_size": 256.0} for v in (3.0, 1.0, 2.0)]
    s = ncu_chain.summarise(ks, {"duration_ns": "gpu__time_duration.sum", "block_size": "launch__block_size",
                                 "missing": "not__collected"})
    assert s == {"a": {"launches": 3, "duration_ns": 2.0, "block_size": 256.0}}


def test_without_ncu_writes_the_reason_and_exits_0(tmp_path, monkeypatch):
    monkeypatch.setattr(ncu_chain, "find_ncu", lambda explicit: None)
    out = tmp_path / "ncu.json"
    assert ncu_chain.main(["--device", "cpu", "--out", str(out)]) == 0
    d = json.loads(out.read_text())
    assert d["status"] == "skipped" and d["ncu"] is None and "not found" in d["reason"]
    assert d["metrics"]["achieved_occupancy_pct"] == "sm__warps_active.avg.pct_of_peak_sustained_active"


def test_highlight_count_is_the_sum_over_flagging_rounds():
    """perf/_bench_chain.COUNTS_CHAIN["dgmc_highlight"]'s closed form against the rounds written out: round r of a
    pixel with f flags has m = N - r active observations; moments 35 m, first eval pass 155 m, the second pass
    160 m only in the rounds that flag (r < f); 6 N flag scans a round; |s| of every light once (6 N)."""
    import _bench_chain

    n = 12
    for f in range(6):
        loop = 6 * n + sum(6 * n + (35 + 155) * (n - r) + (160 * (n - r) if r < f else 0) for r in range(f + 1))
        (b, fl), (ab, _) = _bench_chain.COUNTS_CHAIN["dgmc_highlight"](f, n)
        assert fl == loop
        assert (b, ab) == (12 * n, 5 * n + 1)


def test_roofline_table_puts_each_rows_counters_beside_its_ratio():
    """perf/chain_roofline.py: one line per (row, Warp kernel) with that row's bench ratio, a Taichi row's tasks
    summed into one line, and the reason given for the row in the last column."""
    import chain_roofline

    k = {"launches": 2, "registers_per_thread": 128.0, "theoretical_occupancy_pct": 25.0,
         "achieved_occupancy_pct": 16.5, "issue_slots_pct": 47.7, "fma_pipe_pct": 20.7, "fp64_pipe_pct": 0.0,
         "xu_pipe_pct": 15.6, "dram_throughput_pct": 1.4, "threads_per_warp_inst": 12.9, "duration_ns": 850600.0}
    task = {"launches": 2, "registers_per_thread": 27.0, "achieved_occupancy_pct": 9.0, "issue_slots_pct": 4.0,
            "dram_throughput_pct": 2.4, "duration_ns": 3000.0}
    bench = {"rows": [{"kernel": "pixel_solve_3img", "seconds": 1.393e-3, "ratio": 29.47, "limited_by": "compute"},
                      {"kernel": "rounds_pcg_iteration", "seconds": 2.66e-4, "ratio": 191.2, "limited_by": "memory"}]}
    ncu = {"summary": {"pixel_solve_3img": {"split_starts_kernel__x_cuda_kernel_forward": k,
                                            "split_finish_kernel__x_cuda_kernel_forward": dict(k, duration_ns=12900.0)},
                       "rounds_pcg_iteration": {f"pcg_iteration_c116_0_kernel_{i}_range_for": task for i in range(5)}}}
    out = chain_roofline.lines(bench, ncu, {"pixel_solve_3img": "latency-bound"})
    body = out[2:]
    assert len(body) == 3  # two kernels of the solve, one line for the five Taichi tasks
    assert body[0].startswith("| pixel_solve_3img | 1.393 | 29.5 | compute | split_starts_kernel")
    assert "| 128 | 25.0 / 16.5 | 47.7 | 20.7 | 0.0 | 15.6 | 1.4 | 12.9 | 850.6 | latency-bound |" in body[0]
    assert "(5 tasks)" in body[2] and "| 191.2 |" in body[2] and "| 15.0 |" in body[2]  # 5 x 3 us
    # a Taichi call of two tasks (a serial one and a loop) is folded too, its occupancy read from the loop
    two = {"summary": {"rounds_depth_write": {"depth_write_c146_0_kernel_0_serial": dict(task, achieved_occupancy_pct=1.5),
                                              "depth_write_c146_0_kernel_1_range_for": task}}}
    (line,) = chain_roofline.lines({"rows": []}, two, {})[2:]
    assert "(2 tasks)" in line and "| - / 9.0-9.0 |" in line

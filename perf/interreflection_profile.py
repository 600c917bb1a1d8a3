"""Where a compensation round's time goes: ``gpps.reconstruct_folder`` with ``interreflections="subtract"`` (one
round) on a capture folder, warm (the second of two calls), under cProfile; prints the functions of the
compensation by cumulative time (the flow's ``round_seconds`` gives the totals).

    python perf/interreflection_profile.py FOLDER [--device cuda:0] [--top 25]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> None:
    import gpps

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--device", default=None)
    ap.add_argument("--top", type=int, default=25)
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    cfg = gpps.FolderConfig(interreflections="subtract", interreflection_rounds=1)
    gpps.reconstruct_folder(a.folder, cfg, device=a.device)  # (cold: compiles)
    pr = cProfile.Profile()
    t = time.perf_counter()
    pr.enable()
    res = gpps.reconstruct_folder(a.folder, cfg, device=a.device)
    pr.disable()
    print(f"warm call {time.perf_counter() - t:.3f} s (profiled), MAEN {res.report.get('maen_deg')}, "
          f"round_seconds {res.report['interreflections'].get('round_seconds')}")
    s = io.StringIO()
    st = pstats.Stats(pr, stream=s).sort_stats("cumulative")
    st.print_callees("interreflection_terms")
    st.print_stats(a.top)
    print(s.getvalue())


if __name__ == "__main__":
    main()

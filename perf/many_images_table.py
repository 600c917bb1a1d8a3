"""Session 35's comparison of the robust fits' threshold (``gpps.names.MANY_IMAGES``) on the Mitsuba captures with
4, 5 and 6 lights: the folder flow's rows with robust fits from 7 images (the old threshold 6) and from 4 (the new
3), by material class.

The rows were written by ``perf/dev_held_dark_eval.py OUT GLOBS on`` with ``gpps.flows.folder.MANY_IMAGES`` set
to 6, 4 or 3 for the run (``perf/results/s35/many_{dev4,dev5,dev6,ho4,ho6}_m{6,4,3}_cpu.jsonl``: with 5 and 6 lights
the thresholds 4 and 3 give the same options; the 6-light development rows with 6 are ``dev6_final_cpu.jsonl``'s;
with 4 lights 6 and 4 give the same).  Captures: ``python perf/dev_eval.py --render-only --lights 4,5,6``,
``python perf/heldout_eval.py --render-only --lights 4`` and ``--lights 6``.

Usage:  python perf/many_images_table.py [RESULTS_DIR]
"""
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from held_dark_table import classes as cls  # noqa: E402


def load(path, held_dark_only=False):
    out = {}
    for line in open(path):
        r = json.loads(line)
        if not held_dark_only or r.get("held_dark_refit"):
            out[r["capture"]] = r["maen"]
    return out


def main(d):
    sets = [("development, 4 lights", "many_dev4_m6_cpu.jsonl", "many_dev4_m3_cpu.jsonl"),
            ("development, 5 lights", "many_dev5_m6_cpu.jsonl", "many_dev5_m4_cpu.jsonl"),
            ("development, 6 lights", "dev6_final_cpu.jsonl", "many_dev6_m4_cpu.jsonl"),
            ("held-out, 4 lights", "many_ho4_m4_cpu.jsonl", "many_ho4_m3_cpu.jsonl"),
            ("held-out, 6 lights", "many_ho6_m6_cpu.jsonl", "many_ho6_m4_cpu.jsonl")]
    print("| set | class | n | robust from 7 images | from 4 | better | worse (> 0.05) | largest loss |")
    print("|---|---|---|---|---|---|---|---|")
    for name, a, b in sets:
        A = load(os.path.join(d, a), held_dark_only=a.startswith("dev6_final"))
        B = load(os.path.join(d, b))
        ks = [k for k in B if k in A]
        for c in ("dielectric", "metal", "diffuse"):
            kk = [k for k in ks if cls(k) == c]
            if not kk:
                continue
            ma = sum(A[k] for k in kk) / len(kk)
            mb = sum(B[k] for k in kk) / len(kk)
            print(f"| {name} | {c} | {len(kk)} | {ma:.2f} | {mb:.2f} | {sum(B[k] < A[k] - 0.05 for k in kk)} | "
                  f"{sum(B[k] > A[k] + 0.05 for k in kk)} | {max(B[k] - A[k] for k in kk):.2f} |")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "s35"))

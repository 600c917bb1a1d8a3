"""Per-capture table of perf/dev_held_dark_eval.py's rows (off against on), with the means by material class.

    python perf/held_dark_table.py FILE.jsonl [FILE.jsonl ...]
"""
import json
import sys


def classes(k):
    if "conductor" in k:
        return "metal"
    return "diffuse" if "diffuse" in k else "dielectric"


def main(files):
    for path in files:
        rows = [json.loads(line) for line in open(path)]
        on = {r["capture"]: r["maen"] for r in rows if r["held_dark_refit"]}
        off = {r["capture"]: r["maen"] for r in rows if not r["held_dark_refit"]}
        ks = sorted(k for k in on if k in off)
        print(f"\n{path}\n\n| capture | off | on |\n|---|---|---|")
        for k in ks:
            print(f"| {k.split('-s128')[0]} | {off[k]:.2f} | {on[k]:.2f} |")
        print("\n| class | n | off | on | better | worse (> 0.05 deg) | largest loss |\n|---|---|---|---|---|---|---|")
        for c in ("dielectric", "metal", "non-diffuse", "diffuse"):
            kk = [k for k in ks if (classes(k) != "diffuse" if c == "non-diffuse" else classes(k) == c)]
            if not kk:
                continue
            mo = sum(off[k] for k in kk) / len(kk)
            mn = sum(on[k] for k in kk) / len(kk)
            print(f"| {c} | {len(kk)} | {mo:.2f} | {mn:.2f} | {sum(on[k] < off[k] - 0.05 for k in kk)} | "
                  f"{sum(on[k] > off[k] + 0.05 for k in kk)} | {max(on[k] - off[k] for k in kk):.2f} |")


if __name__ == "__main__":
    main(sys.argv[1:])

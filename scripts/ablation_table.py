#!/usr/bin/env python3
"""The pipeline ablation's table from scripts/ablation.sh's output folder.

  ablation_table.py DIR [--seed S] [--bootstrap B]

Reads DIR/<scene>/<run>/probe/report.json (the paper's headline metrics of the probe's input scene,
"before", and final scene, "after", each after the 5 s evaluation settle) and
DIR/<scene>/<run>/reconstruct_report.json (gt_iou: each object's world-frame voxel IoU against the
ground truth, before and after the probe), and writes DIR/table.md and DIR/table.json:

- one row per pipeline stage, the paper's metrics as means over scenes with 95% bootstrap intervals
  (resampling scenes) for ABO and D_mean;
- per-object world voxel IoU, all objects and the occluded ones (visible < 70%), after the same 5 s
  settle (gt_iou_settled; runs made before reconstruct wrote it fall back to gt_iou, said in the table);
- each row's change from the previous one, paired by scene (bootstrap 95% interval), and row 6 against
  row 5 on the occluded objects, paired by object.

A scene enters only when all five of its runs finished. The four runs sharing the aligned input must
agree on it ("before"); a disagreement is reported, not hidden.
"""
import argparse
import glob
import json
import os
import random
import sys

ROWS = [  # (label, run, which)
    ("1 SAM3D (lifted, settled)", "no_align", "before"),
    ("2 + Align.", "pen", "before"),
    ("3 + Pen.", "pen", "after"),
    ("4 + Grv. (stretch only)", "stretch", "after"),
    ("5 + Re. (base model)", "base", "after"),
    ("6 + Re. (FM-DPO adapter): SimuScene", "tuned", "after"),
]
RUNS = ["no_align", "pen", "stretch", "base", "tuned"]
# (key, header, getter on a headline dict, format)
METRICS = [
    ("iou_2d", "2D IoU", lambda h: h["mask_2d"]["iou"], "{:.3f}"),
    ("abo_2d", "2D ABO", lambda h: h["mask_2d"]["abo"], "{:.3f}"),
    ("abo_2d_fhfo", "2D ABO fh/fo", lambda h: h["mask_2d"]["abo_fhfo"], "{:.3f}"),
    ("iou_3d", "3D IoU", lambda h: h["box_3d"]["iou"], "{:.3f}"),
    ("abo_3d", "3D ABO", lambda h: h["box_3d"]["abo"], "{:.3f}"),
    ("abo_3d_fhfo", "3D ABO fh/fo", lambda h: h["box_3d"]["abo_fhfo"], "{:.3f}"),
    ("stability", "stab. %", lambda h: h["physics"]["stability"], "{:.1f}"),
    ("penetration", "pen. %", lambda h: h["physics"]["penetration_ratio"], "{:.1f}"),
    ("d_mean", "D_mean m", lambda h: h["physics"]["mean_displacement"], "{:.3f}"),
    ("e_pk", "E_pk J", lambda h: h["physics"]["peak_energy"], "{:.2f}"),
]
OCCLUDED = 0.7  # visible fraction below this: an occluded object


def load(path):
    with open(path) as f:
        return json.load(f)


def mean(xs):
    return sum(xs) / len(xs) if xs else float("nan")


def boot_ci(xs, rng, b):
    """95% percentile bootstrap interval of the mean of xs."""
    if len(xs) < 2:
        return [float("nan"), float("nan")]
    n = len(xs)
    ms = sorted(mean([xs[rng.randrange(n)] for _ in range(n)]) for _ in range(b))
    return [ms[int(0.025 * b)], ms[int(0.975 * b) - 1]]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dir")
    ap.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    ap.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples (default 2000)")
    a = ap.parse_args()
    rng = random.Random(a.seed)

    scenes, skipped, mismatch, sources = [], [], [], set()
    for sdir in sorted(glob.glob(os.path.join(a.dir, "test_*"))):
        if not os.path.isdir(sdir):
            continue
        name = os.path.basename(sdir)
        runs = {}
        for r in RUNS:
            rep = os.path.join(sdir, r, "probe", "report.json")
            rec = os.path.join(sdir, r, "reconstruct_report.json")
            if not (os.path.exists(os.path.join(sdir, r, "done")) and os.path.exists(rep) and os.path.exists(rec)):
                break
            rr = load(rec)
            # The voxel IoU after the 5 s evaluation settles (the scenes the headline metrics score) when
            # reconstruct wrote it, else of the unsettled scenes (older runs; said in the table).
            src = "gt_iou_settled" if "gt_iou_settled" in rr else "gt_iou"
            sources.add(src)
            runs[r] = {"headline": load(rep)["headline"], "gt": rr[src]["objects"]}
        if len(runs) < len(RUNS):
            skipped.append(name)
            continue
        # The runs that share the aligned input must agree on it.
        ref = runs["pen"]
        for r in ("stretch", "base", "tuned"):
            d = abs(runs[r]["headline"]["before"]["mask_2d"]["abo"] - ref["headline"]["before"]["mask_2d"]["abo"])
            g = max((abs((x["gt_iou_before"] or 0) - (y["gt_iou_before"] or 0))
                     for x, y in zip(runs[r]["gt"], ref["gt"])), default=0)
            if d > 1e-9 or g > 1e-9:
                mismatch.append(f"{name}/{r}: before differs from pen's (2D ABO by {d:.2e}, voxel IoU by {g:.2e})")
        scenes.append((name, runs))
    if not scenes:
        sys.exit(f"ablation_table.py: no finished scene under {a.dir} (each needs the runs {RUNS})")

    # Per row: per-scene metric values, per-object voxel IoU.
    table = []
    for label, run, which in ROWS:
        per_scene = {k: [] for k, *_ in METRICS}
        vox_all, vox_occ, n_resampled = [], [], 0
        for _, runs in scenes:
            h = runs[run]["headline"][which]
            for k, _, get, _ in METRICS:
                per_scene[k].append(get(h))
            for o in runs[run]["gt"]:
                v = o["gt_iou_" + which] or 0.0  # an object missing from the scene scores 0 (as gt_iou's mean)
                vox_all.append(v)
                if o["visible_fraction"] < OCCLUDED:
                    vox_occ.append(v)
                if which == "after" and o.get("resampled"):
                    n_resampled += 1
        table.append({"row": label, "run": run, "which": which, "per_scene": per_scene,
                      "vox_all": vox_all, "vox_occ": vox_occ, "n_resampled": n_resampled})

    out = {"dir": a.dir, "scenes": [s for s, _ in scenes], "skipped_unfinished": skipped,
           "before_mismatch": mismatch, "voxel_source": sorted(sources), "occluded_below": OCCLUDED, "bootstrap": a.bootstrap, "rows": []}
    lines = [f"{len(scenes)} scenes ({sum(len(r['pen']['gt']) for _, r in scenes)} objects, "
             f"{len(table[0]['vox_occ'])} occluded < {int(100 * OCCLUDED)}% visible); means over scenes, "
             f"[95% bootstrap interval over scenes]; voxel IoU: world-frame, mean over objects, "
             + ("after the 5 s evaluation settle like every other column." if sources == {"gt_iou_settled"} else
                f"from {sorted(sources)} (gt_iou: rows 1-2 unsettled, rows 3-6 after the probe's final settle)."), ""]
    hdr = ["row"] + [h for _, h, _, _ in METRICS] + ["voxel IoU all", "voxel IoU occl.", "resampled"]
    lines.append("| " + " | ".join(hdr) + " |")
    lines.append("|---|" + "---:|" * (len(hdr) - 1))
    for t in table:
        cells = [t["row"]]
        row = {"row": t["row"], "run": t["run"], "which": t["which"], "metrics": {}}
        for k, _, _, f in METRICS:
            xs = t["per_scene"][k]
            m = mean(xs)
            ci = boot_ci(xs, rng, a.bootstrap) if k in ("abo_2d", "abo_3d_fhfo", "d_mean") else None
            row["metrics"][k] = {"mean": m, "ci95": ci}
            cells.append(f.format(m) + (f" [{f.format(ci[0])}, {f.format(ci[1])}]" if ci else ""))
        row["voxel_iou_all"] = mean(t["vox_all"])
        row["voxel_iou_occluded"] = mean(t["vox_occ"])
        row["n_resampled"] = t["n_resampled"]
        cells += [f"{row['voxel_iou_all']:.3f}", f"{row['voxel_iou_occluded']:.3f}", str(t["n_resampled"])]
        lines.append("| " + " | ".join(cells) + " |")
        out["rows"].append(row)

    # Each stage against the previous one, paired by scene; row 6 vs 5 on occluded objects, by object.
    lines += ["", "Change from the previous row (paired by scene; 95% bootstrap interval):", ""]
    keys = ["abo_2d", "abo_2d_fhfo", "abo_3d", "abo_3d_fhfo", "stability", "d_mean"]
    lines.append("| change | " + " | ".join(h for k, h, _, _ in METRICS if k in keys) + " | voxel IoU all (by object) |")
    lines.append("|---|" + "---:|" * (len(keys) + 1))
    out["changes"] = []
    for i in range(1, len(table)):
        p, c = table[i - 1], table[i]
        cells, ch = [f"{p['row'].split()[0]} -> {c['row'].split()[0]}"], {"from": p["row"], "to": c["row"]}
        for k, _, _, f in METRICS:
            if k not in keys:
                continue
            d = [y - x for x, y in zip(p["per_scene"][k], c["per_scene"][k])]
            ci = boot_ci(d, rng, a.bootstrap)
            ch[k] = {"delta": mean(d), "ci95": ci}
            cells.append(f"{mean(d):+.3f} [{ci[0]:+.3f}, {ci[1]:+.3f}]")
        d = [y - x for x, y in zip(p["vox_all"], c["vox_all"])]
        ci = boot_ci(d, rng, a.bootstrap)
        ch["voxel_iou_all"] = {"delta": mean(d), "ci95": ci}
        cells.append(f"{mean(d):+.3f} [{ci[0]:+.3f}, {ci[1]:+.3f}]")
        lines.append("| " + " | ".join(cells) + " |")
        out["changes"].append(ch)

    # Row 6 against row 5 on the occluded objects (the shape claim), and on those both resampled.
    t5, t6 = table[4], table[5]
    d = [y - x for x, y in zip(t5["vox_occ"], t6["vox_occ"])]
    ci = boot_ci(d, rng, a.bootstrap)
    both = []
    for _, runs in scenes:
        for x, y in zip(runs["base"]["gt"], runs["tuned"]["gt"]):
            if x["visible_fraction"] < OCCLUDED and x.get("resampled") and y.get("resampled"):
                both.append((y["gt_iou_after"] or 0) - (x["gt_iou_after"] or 0))
    ci_b = boot_ci(both, rng, a.bootstrap)
    out["row6_vs_row5_occluded"] = {"n": len(d), "delta": mean(d), "ci95": ci,
                                    "resampled_in_both": {"n": len(both), "delta": mean(both), "ci95": ci_b}}
    lines += ["", f"Row 6 against row 5, occluded objects (< {int(100 * OCCLUDED)}% visible), world voxel IoU, "
              f"paired by object: {mean(d):+.4f} [{ci[0]:+.4f}, {ci[1]:+.4f}] (n = {len(d)}); those resampled in "
              f"both runs: {mean(both):+.4f} [{ci_b[0]:+.4f}, {ci_b[1]:+.4f}] (n = {len(both)})."]
    if mismatch:
        lines += ["", f"WARNING: {len(mismatch)} run(s) disagree with 'pen' on the shared input: " + "; ".join(mismatch[:5])]
    if skipped:
        lines += ["", f"Left out (unfinished): {', '.join(skipped)}"]
    md = "\n".join(lines) + "\n"
    for name, text in (("table.md", md), ("table.json", json.dumps(out, indent=1) + "\n")):
        tmp = os.path.join(a.dir, name + ".tmp")
        with open(tmp, "w") as f:
            f.write(text)
        os.replace(tmp, os.path.join(a.dir, name))
    print(md, end="")


if __name__ == "__main__":
    main()

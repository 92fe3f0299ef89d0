#!/usr/bin/env python3
"""The demo's resampling showcase (scripts/demo.sh, step 6): which object, and what resampling did to it.

  demo_showcase.py pick GT_JSON
      prints the id of the scene's most occluded object: the lowest visible_fraction in a shape-world
      scene's gt.json (world scenes; the first one on a tie).
  demo_showcase.py branch RECONSTRUCT_DIR ID
      prints the probe's branch for ID in that reconstruct run (probe/report.json), "" when absent.
  demo_showcase.py report PROBE_RUN_DIR SHOWCASE_DIR ID
      prints ID's ground-truth IoU before the probe and after it in the showcase run (reconstruct --gt,
      reconstruct_report.json gt_iou), what the probe's own run did with it, its candidates and the
      path of its candidates picture.
"""
import json
import os
import sys


def fail(msg):
    sys.exit(f"demo_showcase.py: {msg}")


def load(path):
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as e:
        fail(f"{path}: {e}")


def pick(gt_path):
    objs = load(gt_path).get("objects") or fail(f"{gt_path}: no 'objects'")
    for o in objs:
        if "id" not in o or "visible_fraction" not in o:
            fail(f"{gt_path}: an object without 'id' or 'visible_fraction': {o}")
    print(min(objs, key=lambda o: o["visible_fraction"])["id"])


def probe_entry(run_dir, oid):
    for o in load(f"{run_dir}/probe/report.json").get("objects", []):
        if o.get("id") == oid:
            return o
    return None


def gt_row(run_dir, oid):
    path = f"{run_dir}/reconstruct_report.json"
    for r in load(path).get("gt_iou", {}).get("objects", []):
        if r.get("id") == oid:
            return r
    fail(f"{path}: no gt_iou row for object '{oid}' (was reconstruct run with --gt?)")


def iou(v):
    return "-" if v is None else f"{v:.3f}"


def report(probe_run, showcase, oid):
    plain, forced = gt_row(probe_run, oid), gt_row(showcase, oid)
    entry = probe_entry(showcase, oid) or fail(f"{showcase}/probe/report.json: no object '{oid}'")
    rs = entry.get("resample", {})
    print(f"   object               {oid} ({forced['family']}, {100 * forced['visible_fraction']:.0f}% visible), "
          f"rho {entry.get('rho', float('nan')):.3f}")
    print(f"   IoU before the probe {iou(forced['gt_iou_before'])}   (lifted and aligned)")
    print(f"   IoU after resampling {iou(forced['gt_iou_after'])}   "
          f"({'replaced by the kept candidate' if rs.get('resampled') else 'NOT replaced: ' + entry.get('message', '')})")
    if os.path.realpath(probe_run) != os.path.realpath(showcase):
        print(f"   the probe's own run  {iou(plain['gt_iou_after'])}   (step 5: branch {plain['branch']})")
    cands = rs.get("candidates", [])
    if cands:
        kept = rs.get("chosen_candidate", -1)
        moves = ", ".join(f"#{k} {c['displacement'] * 1000:.1f} mm{' (kept)' if k == kept else ''}"
                          + ("" if c.get("ok") else " (failed)") for k, c in enumerate(cands))
        print(f"   candidates           {len(cands)}, motion in their settle: {moves}")
    # The probe names it candidates_<id>.png, the id made file-name safe (probe_world.h safe_name).
    safe = "".join(ch if ch.isascii() and (ch.isalnum() or ch in "-_") else "_" for ch in oid) or "object"
    picture = f"{showcase}/probe/candidates_{safe}.png"
    print(f"   candidates picture   {picture if os.path.exists(picture) else '(none: fewer than two usable candidates)'}")
    if "forced_resample" in entry.get("flags", []):
        print("   resampling is the paper's response to rho >= 0.15; here it is forced to show it")
    else:
        print("   the probe resampled it on its own: its rho >= 0.15, the paper's threshold")


def main():
    args = sys.argv[1:]
    if not args or args[0] in ("-h", "--help"):
        print(__doc__)
        sys.exit(0 if args else 2)
    if args[0] == "pick" and len(args) == 2:
        pick(args[1])
    elif args[0] == "branch" and len(args) == 3:
        entry = probe_entry(args[1], args[2]) if os.path.exists(f"{args[1]}/probe/report.json") else None
        print(entry.get("branch", "") if entry else "")
    elif args[0] == "report" and len(args) == 4:
        report(*args[1:])
    else:
        fail(f"bad arguments {args}; see --help")


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""The reconstruct sidecar (objects.json) of a shape-world scene folder (world scenes' output).

  world_sidecar.py SCENE_DIR [--table box|lift] [--quiet]

Floor, wall and table come from the label image. The table is a fixed base, fitted as a box to its
mask's depth (--table box, the default: `"fit": "box"`, docs/reconstruct.md) or lifted by the model
like an object (--table lift: the miniature never saw a scene table). Every object keeps its
ground-truth id so that `reconstruct --gt SCENE_DIR/gt.json` can match it. Prints one line per object
(family, size, visible fraction) unless --quiet.
"""
import json
import sys


def main():
    if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        sys.exit(0 if len(sys.argv) >= 2 else 2)
    d = sys.argv[1]
    table = "box"
    if "--table" in sys.argv:
        i = sys.argv.index("--table")
        table = sys.argv[i + 1] if i + 1 < len(sys.argv) else ""
        if table not in ("box", "lift"):
            sys.exit(f"world_sidecar.py: --table '{table}' (box, lift)")
    gt = json.load(open(f"{d}/gt.json"))
    lab = gt["labels"]
    objs = [{"label_value": lab["floor"], "id": "floor", "role": "floor"},
            {"label_value": lab["wall"], "id": "wall", "role": "wall"},
            {"label_value": lab["table"], "id": "table", "label": "table", "base": True, "fit": table}]
    objs += [{"label_value": o["label"], "id": o["id"], "label": o["family"]} for o in gt["objects"]]
    tmp = f"{d}/objects.json.tmp"
    with open(tmp, "w") as f:
        json.dump({"objects": objs}, f, indent=1)
    import os
    os.replace(tmp, f"{d}/objects.json")
    if "--quiet" not in sys.argv:
        for o in gt["objects"]:
            print(f"   {o['id']:<22} {o['family']:<11} {o['size_m'] * 100:5.1f} cm  visible {100 * o['visible_fraction']:3.0f}%"
                  + ("  (occluded target)" if o["target"] else ""))


if __name__ == "__main__":
    main()

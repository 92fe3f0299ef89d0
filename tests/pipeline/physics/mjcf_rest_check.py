#!/usr/bin/env python3
"""Rest check of probe-written scene.xml files in the PyPI `mujoco` (the simulator users open them in).

For every file: compile it, step `--seconds` of simulated time from the written state, and measure
how far each free-joint body moved. Fails (exit 1) when a body moves >= --limit metres, when MuJoCo
raises any warning (compile-time Python warnings or a data.warning counter), or when a file does not
load. Prints one JSON line per file: {"file", "mujoco", "integrator", "max_displacement", "per_body",
"warnings"}.

    python tests/pipeline/physics/mjcf_rest_check.py OUT/scene.xml [more.xml ...] [--seconds 5] [--limit 0.002]
"""
import argparse
import json
import sys
import warnings

import mujoco
import numpy as np


def check(path, seconds):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = mujoco.MjModel.from_xml_path(path)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        free = [b for b in range(model.nbody)
                if model.body_jntnum[b] >= 1 and model.jnt_type[model.body_jntadr[b]] == mujoco.mjtJoint.mjJNT_FREE]
        start = {b: data.xpos[b].copy() for b in free}
        peak = {b: 0.0 for b in free}
        for _ in range(int(round(seconds / model.opt.timestep))):
            mujoco.mj_step(model, data)
            for b in free:
                peak[b] = max(peak[b], float(np.linalg.norm(data.xpos[b] - start[b])))
    found = [str(w.message) for w in caught]
    for i, w in enumerate(data.warning):
        if w.number > 0:
            found.append(f"{mujoco.mjtWarning(i).name} x{w.number}")
    per_body = {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b): peak[b] for b in free}
    integrator = mujoco.mjtIntegrator(model.opt.integrator).name
    return {"file": path, "mujoco": mujoco.__version__, "integrator": integrator,
            "max_displacement": max(per_body.values(), default=0.0), "per_body": per_body, "warnings": found}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("files", nargs="+")
    ap.add_argument("--seconds", type=float, default=5.0, help="simulated time (paper's evaluation settle: 5 s)")
    ap.add_argument("--limit", type=float, default=0.002, help="largest allowed motion of a free body (m)")
    a = ap.parse_args()
    bad = 0
    for f in a.files:
        try:
            r = check(f, a.seconds)
        except Exception as e:  # a file that does not load is a failure, named
            print(json.dumps({"file": f, "error": str(e)}))
            bad += 1
            continue
        print(json.dumps(r))
        if r["warnings"] or not r["max_displacement"] < a.limit:
            bad += 1
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()

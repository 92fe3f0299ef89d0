#!/usr/bin/env python3
"""Writes the small procedural meshes of tests/testdata/meshes (eval_lift --objects in CI): each made
here from a formula, in its own file format and unit, so the folder exercises OBJ / PLY / STL reading and
the unit guess of world::make_external_shape (the longest side read in m, cm, mm or inches, whichever
first lands in 2-60 cm). No third-party meshes. Deterministic: rerunning rewrites identical bytes.

    python3 scripts/make_test_meshes.py [OUT_DIR]   (default tests/testdata/meshes)
"""
import math
import os
import struct
import sys


def box(sx, sy, sz):
    """Axis-aligned box centred at the origin, outward counter-clockwise triangles."""
    v = [((i & 1 and 1 or -1) * sx / 2, (i & 2 and 1 or -1) * sy / 2, (i & 4 and 1 or -1) * sz / 2) for i in range(8)]
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    f = []
    for a, b, c, d in quads:
        f += [(a, b, c), (a, c, d)]
    return v, f


def lathe(profile, segments):
    """Surface of revolution about y of a (y, radius) profile, capped at both ends."""
    v = [(0.0, profile[0][0], 0.0)]
    for y, r in profile:
        for i in range(segments):
            t = 2 * math.pi * i / segments
            v.append((r * math.cos(t), y, r * math.sin(t)))
    v.append((0.0, profile[-1][0], 0.0))
    ring = lambda k, i: 1 + k * segments + i % segments
    bottom = len(v) - 1
    f = []
    for i in range(segments):
        f.append((0, ring(0, i), ring(0, i + 1)))
        f.append((bottom, ring(len(profile) - 1, i + 1), ring(len(profile) - 1, i)))
        for k in range(len(profile) - 1):
            f.append((ring(k, i), ring(k + 1, i), ring(k + 1, i + 1)))
            f.append((ring(k, i), ring(k + 1, i + 1), ring(k, i + 1)))
    return v, f


def prism(poly, depth):
    """A counter-clockwise polygon in xy, star-shaped about its first vertex (caps fanned from it), extruded
    over z in [-depth/2, depth/2]."""
    n = len(poly)
    v = [(x, y, -depth / 2) for x, y in poly] + [(x, y, depth / 2) for x, y in poly]
    f = []
    for i in range(1, n - 1):
        f.append((0, i + 1, i))          # back cap (-z), clockwise seen from +z
        f.append((n, n + i, n + i + 1))  # front cap (+z)
    for i in range(n):
        j = (i + 1) % n
        f += [(i, j, n + j), (i, n + j, n + i)]
    return v, f


def fmt(x):
    return f"{x:.6g}"


def write_obj(path, v, f, comment):
    with open(path, "w") as out:
        out.write(f"# {comment}\n")
        for p in v:
            out.write("v " + " ".join(fmt(c) for c in p) + "\n")
        for t in f:
            out.write("f " + " ".join(str(i + 1) for i in t) + "\n")


def write_ply(path, v, f, comment):
    with open(path, "w") as out:
        out.write(f"ply\nformat ascii 1.0\ncomment {comment}\nelement vertex {len(v)}\n"
                  "property float x\nproperty float y\nproperty float z\n"
                  f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
        for p in v:
            out.write(" ".join(fmt(c) for c in p) + "\n")
        for t in f:
            out.write("3 " + " ".join(str(i) for i in t) + "\n")


def write_stl(path, v, f, comment):
    with open(path, "wb") as out:
        out.write(comment.encode()[:80].ljust(80, b" "))
        out.write(struct.pack("<I", len(f)))
        for a, b, c in f:
            pa, pb, pc = v[a], v[b], v[c]
            u = [pb[i] - pa[i] for i in range(3)]
            w = [pc[i] - pa[i] for i in range(3)]
            n = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]]
            norm = math.sqrt(sum(x * x for x in n)) or 1.0
            out.write(struct.pack("<12fH", *(x / norm for x in n), *pa, *pb, *pc, 0))


def main():
    out = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "..", "tests", "testdata", "meshes")
    os.makedirs(out, exist_ok=True)
    # A 12 x 8 x 5 cm box in centimetres (OBJ).
    write_obj(os.path.join(out, "box_cm.obj"), *box(12, 8, 5), "box 12 x 8 x 5, centimetres (scripts/make_test_meshes.py)")
    # A cylinder 90 mm tall, 50 mm across, in millimetres (binary STL).
    write_stl(os.path.join(out, "cylinder_mm.stl"), *lathe([(-45, 25), (45, 25)], 24),
              "cylinder h 90 d 50, millimetres (scripts/make_test_meshes.py)")
    # A truncated cone 15 cm tall in metres (ASCII PLY).
    write_ply(os.path.join(out, "cone_m.ply"), *lathe([(-0.075, 0.012), (0.075, 0.05)], 24),
              "truncated cone h 0.15, metres (scripts/make_test_meshes.py)")
    # An L-bracket 10 x 6 cm, 3 cm deep, in centimetres (OBJ).
    write_obj(os.path.join(out, "l_bracket_cm.obj"),
              *prism([(0, 0), (10, 0), (10, 2), (2, 2), (2, 6), (0, 6)], 3), "L-bracket 10 x 6 x 3, centimetres")


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Self-check of open3d_peers.py, and a quick accuracy summary. Standard library only.

    python3 benches/peers/test_open3d_peers.py
        writes three small synthetic cases to a temporary folder (a global one: the model
        rotated by 120° and moved 2.8 away; a local one: rotated by 4°; a broken one without
        target.ply), runs every method with the venv's Python, runs --check and asserts that
        the run survived the broken case, that every pose is a rotation, and that
        fpfh-ransac-icp solves the global case and icp-p2p the local one.

    python3 benches/peers/test_open3d_peers.py --summarise results.jsonl --cases DIR
        rotation error arccos((tr(R̂ᵀR) − 1)/2) and translation error ‖t̂ − t‖ against each
        case's gt.json: per method, the median, the accuracy at 5/10/15° and the median time.
        (A sanity view only: the scores that count are computed in Rust.)

The Python that runs open3d_peers.py is $PEERS_PYTHON, else target/peers-venv/bin/python
under the repository root, else this interpreter.
"""

import json
import math
import os
import random
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
SCRIPT = HERE / "open3d_peers.py"
REPO = HERE.parent.parent


def peers_python():
    if os.environ.get("PEERS_PYTHON"):
        return os.environ["PEERS_PYTHON"]
    venv = REPO / "target" / "peers-venv" / "bin" / "python"
    return str(venv) if venv.exists() else sys.executable


# --- small linear algebra on lists -------------------------------------------------------------


def matmul(a, b):
    return [[sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)] for i in range(3)]


def transpose(a):
    return [list(r) for r in zip(*a)]


def apply(R, t, p):
    return [sum(R[i][k] * p[k] for k in range(3)) + t[i] for i in range(3)]


def axis_angle(axis, deg):
    n = math.sqrt(sum(x * x for x in axis))
    x, y, z = (c / n for c in axis)
    a = math.radians(deg)
    c, s, C = math.cos(a), math.sin(a), 1 - math.cos(a)
    return [[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
            [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
            [z * x * C - y * s, z * y * C + x * s, c + z * z * C]]


def rotation_error_deg(R_est, R_gt):
    m = matmul(transpose(R_est), R_gt)
    c = (m[0][0] + m[1][1] + m[2][2] - 1) / 2
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def translation_error(t_est, t_gt):
    return math.sqrt(sum((a - b) ** 2 for a, b in zip(t_est, t_gt)))


# --- synthetic cases ---------------------------------------------------------------------------


def write_ply(path, points):
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex %d\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n" % len(points))
    with open(path, "wb") as f:
        f.write(header.encode())
        for p in points:
            f.write(struct.pack("<3f", *p))


def box_surface(rng, n):
    """n points on the surfaces of three overlapping boxes (an asymmetric object in [-1, 1])."""
    boxes = [((0.0, 0.0, 0.0), (2.0, 0.6, 0.6)), ((0.6, 0.55, 0.0), (0.4, 0.5, 0.4)),
             ((-0.6, 0.0, 0.45), (0.3, 0.3, 0.3))]
    faces = []
    for c, s in boxes:
        for axis in range(3):
            u, v = [a for a in range(3) if a != axis]
            for sign in (-1, 1):
                faces.append((c, s, axis, u, v, sign, s[u] * s[v]))
    total = sum(f[-1] for f in faces)
    pts = []
    for _ in range(n):
        r = rng.random() * total
        for c, s, axis, u, v, sign, area in faces:
            r -= area
            if r <= 0:
                break
        p = [0.0, 0.0, 0.0]
        p[axis] = c[axis] + sign * s[axis] / 2
        p[u] = c[u] + (rng.random() - 0.5) * s[u]
        p[v] = c[v] + (rng.random() - 0.5) * s[v]
        pts.append(p)
    return pts


def make_case(folder, source, R, t, with_target=True):
    folder.mkdir(parents=True)
    write_ply(folder / "source.ply", source)
    if with_target:
        write_ply(folder / "target.ply", [apply(R, t, p) for p in source])
    (folder / "gt.json").write_text(json.dumps({"R": R, "t": t}))
    (folder / "meta.json").write_text(json.dumps({"set": "synthetic"}))


def self_check():
    rng = random.Random(0)
    source = box_surface(rng, 1500)
    with tempfile.TemporaryDirectory() as tmp:
        cases, out = Path(tmp) / "cases", Path(tmp) / "results.jsonl"
        make_case(cases / "case_a_global", source, axis_angle((1, 2, 3), 120), [0.1, -0.2, 2.8])
        make_case(cases / "case_b_local", source, axis_angle((0, 1, 0), 4), [0.02, 0.0, 0.03])
        make_case(cases / "case_c_broken", source, axis_angle((0, 0, 1), 10), [0, 0, 0], with_target=False)
        py = peers_python()
        cmd = [py, str(SCRIPT), "--cases", str(cases), "--out", str(out), "--seed", "0", "--threads", "1"]
        print("running:", " ".join(cmd))
        run = subprocess.run(cmd, capture_output=True, text=True)
        assert run.returncode == 0, f"peers run failed ({run.returncode}):\n{run.stdout}\n{run.stderr}"
        assert run.stdout.startswith("open3d_peers seed 0 config {"), run.stdout[:200]
        chk = subprocess.run([py, str(SCRIPT), "--check", "--cases", str(cases), "--out", str(out)],
                             capture_output=True, text=True)
        print(chk.stdout.strip())
        assert chk.returncode == 0, "--check failed"
        recs = {(r["case"], r["method"]): r for r in map(json.loads, out.read_text().splitlines())}
        assert len(recs) == 15, len(recs)
        for (case, method), r in recs.items():
            if case == "case_c_broken":
                assert not r["ok"] and "target.ply" in r["error"] and r["R"] is None, r
                continue
            assert r["ok"], r
            R = r["R"]
            e = [[sum(R[i][k] * R[j][k] for k in range(3)) - (i == j) for j in range(3)] for i in range(3)]
            assert max(abs(x) for row in e for x in row) < 1e-6, f"{case} {method}: R not orthonormal"
        errors = {}
        for case in ("case_a_global", "case_b_local"):
            gt = json.loads((cases / case / "gt.json").read_text())
            for m in ("icp-p2p", "icp-p2l", "fpfh-ransac", "fpfh-ransac-icp", "fgr"):
                r = recs[(case, "o3d-" + m)]
                errors[(case, m)] = (rotation_error_deg(r["R"], gt["R"]), translation_error(r["t"], gt["t"]))
                print(f"  {case:15s} o3d-{m:16s} rot {errors[(case, m)][0]:7.2f}°  trans {errors[(case, m)][1]:.4f}"
                      f"  {r['seconds']:.3f}s")
        assert errors[("case_a_global", "fpfh-ransac-icp")][0] < 2.0, "fpfh-ransac-icp missed the global case"
        assert errors[("case_b_local", "icp-p2p")][0] < 1.0, "icp-p2p missed the local case"
        # Same seed, one thread: the same poses (repeatability).
        out2 = Path(tmp) / "again.jsonl"
        cmd2 = cmd[:5] + [str(out2)] + cmd[6:] + ["--methods", "fpfh-ransac,fgr"]
        assert subprocess.run(cmd2, capture_output=True, text=True).returncode == 0
        again = {(r["case"], r["method"]): r for r in map(json.loads, out2.read_text().splitlines())}
        for key, r in again.items():
            assert r["R"] == recs[key]["R"] and r["t"] == recs[key]["t"], f"{key} not repeatable"
    print("self-check PASS")
    return 0


def summarise(results, cases):
    recs = [json.loads(line) for line in Path(results).read_text().splitlines() if line.strip()]
    by_method = {}
    for r in recs:
        gt = json.loads((Path(cases) / r["case"] / "gt.json").read_text())
        row = by_method.setdefault(r["method"], {"rot": [], "trans": [], "sec": [], "failed": 0})
        row["sec"].append(r["seconds"])
        if not r["ok"]:
            row["failed"] += 1
            row["rot"].append(180.0)
            row["trans"].append(math.inf)
            continue
        row["rot"].append(rotation_error_deg(r["R"], gt["R"]))
        row["trans"].append(translation_error(r["t"], gt["t"]))

    def median(xs):
        xs = sorted(xs)
        k = len(xs)
        return (xs[(k - 1) // 2] + xs[k // 2]) / 2

    print(f"{'method':22s} {'n':>4s} {'fail':>4s} {'med rot°':>9s} {'<5°':>5s} {'<10°':>5s} {'<15°':>5s} "
          f"{'med ‖Δt‖':>9s} {'med s':>8s} {'mean s':>8s}")
    for m, row in by_method.items():
        n = len(row["rot"])
        acc = [sum(e < th for e in row["rot"]) / n for th in (5, 10, 15)]
        print(f"{m:22s} {n:4d} {row['failed']:4d} {median(row['rot']):9.2f} {acc[0]:5.2f} {acc[1]:5.2f} "
              f"{acc[2]:5.2f} {median(row['trans']):9.3f} {median(row['sec']):8.3f} "
              f"{sum(row['sec']) / n:8.3f}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--summarise" and sys.argv[3] == "--cases":
        sys.exit(summarise(sys.argv[2], sys.argv[4]))
    if len(sys.argv) > 1:
        sys.exit(__doc__)
    sys.exit(self_check())

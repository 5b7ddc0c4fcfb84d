#!/usr/bin/env python3
"""Self-check of open3d_peers.py, and a quick accuracy summary. Standard library only.

    python3 benches/peers/test_open3d_peers.py
        writes three small synthetic cases to a temporary folder (a global one: the model
        rotated by 120° and moved 2.8 away; a local one: rotated by 4°; a broken one without
        target.ply), runs every method with the venv's Python, runs --check and asserts that
        the run survived the broken case, that every pose is a rotation, and that
        fpfh-ransac-icp solves the global case and icp-p2p the local one. Then the timing
        mode's tests: `--points` sizes N and MxN (bad ones are usage errors), the records'
        points / observed_points, and the pairs each size draws. The last runs timing() in
        this interpreter and is skipped unless it has numpy and Open3D (the venv's Python has).

    target/peers-venv/bin/python -m pytest benches/peers/test_open3d_peers.py
        the same tests with pytest (skipped ones: Open3D missing).

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
import unittest
from pathlib import Path

HERE = Path(__file__).resolve().parent
SCRIPT = HERE / "open3d_peers.py"
REPO = HERE.parent.parent
sys.path.insert(0, str(HERE))

import open3d_peers  # noqa: E402  (standard library at import time, like peers_common)
import peers_common  # noqa: E402


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


def has_open3d(python):
    return subprocess.run([python, "-c", "import numpy, open3d"], capture_output=True).returncode == 0


def test_self_check():
    if not has_open3d(peers_python()):
        raise unittest.SkipTest(f"{peers_python()} cannot import open3d")
    assert self_check() == 0


def test_bad_points_are_usage_errors():
    """--points takes N or MxN entries; anything else stops before any work (no Open3D needed)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "t.json"
        for bad in ("512,0", "1024x", "12x3x4", "abc", "-5", ""):
            proc = subprocess.run([sys.executable, str(SCRIPT), "--timing", "--out", str(out), f"--points={bad}"],
                                  capture_output=True, text=True)
            assert proc.returncode == 2 and "usage:" in proc.stderr and "--points" in proc.stderr, (bad, proc.stderr)
            assert not out.exists()
    assert open3d_peers.parse_args(["--timing", "--out", "t.json", "--points", "256, 300x200"]).sizes == [
        (256, 256), (300, 200)]
    assert open3d_peers.parse_args(["--timing", "--out", "t.json"]).sizes == [(512, 512), (1024, 1024), (2048, 2048)]


def test_timing_writes_points_and_observed_points():
    """A real timing run on the synthetic pair: one record per (size, method) with the model
    and observed counts, the config's sizes as given and `n=MxN` in the log."""
    py = peers_python()
    if not has_open3d(py):
        raise unittest.SkipTest(f"{py} cannot import open3d")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "timing.json"
        proc = subprocess.run([py, str(SCRIPT), "--timing", "--points", "512,600x400", "--repeats", "1", "--out",
                               str(out), "--methods", "icp-p2p,fpfh-ransac", "--threads", "1"],
                              capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        config = json.loads(proc.stdout.splitlines()[0].split(" config ", 1)[1])
        assert config["points"] == ["512", "600x400"], config["points"]
        assert "o3d-icp-p2p n=600x400 median" in proc.stderr and "o3d-icp-p2p n=512 median" in proc.stderr
        report = json.loads(out.read_text())
        got = [(r["method"], r["points"], r["observed_points"]) for r in report["results"]]
        assert got == [("o3d-icp-p2p", 512, 512), ("o3d-fpfh-ransac", 512, 512), ("o3d-icp-p2p", 600, 400),
                       ("o3d-fpfh-ransac", 600, 400)], got
        for r in report["results"]:
            assert r["ok"] and r["median_seconds"] > 0 and len(r["runs"]) == 1, r
        fpfh = [r for r in report["results"] if r["method"] == "o3d-fpfh-ransac"]
        assert all(0 < r["source_down"] <= r["points"] and 0 < r["target_down"] <= r["observed_points"] for r in fpfh)


def probe_pipeline(run):
    """A stand-in for open3d_peers.Pipeline whose `run(method, source, target)` is `run`."""

    class Probe:
        def __init__(self, o3d, args):
            pass

        def config(self):
            return {}

        def run(self, method, source, target):
            return run(method, source, target)

    return Probe


def test_timing_resamples_the_model_and_the_observed_points_to_each_size():
    """In this interpreter (numpy and Open3D needed): a pair entry MxN resamples source.ply to M
    and target.ply to N points with the key "MxN"; a square entry N keeps the key str(N), the
    draws of plain `--points N` (and of ppf_peers.py's timing)."""
    try:
        import numpy as np
        import open3d  # noqa: F401
    except ImportError as e:
        raise unittest.SkipTest(f"needs numpy and open3d: {e}")
    calls, seeds = [], []

    def run(method, source, target):
        calls.append((method, np.array(source), np.array(target)))
        return np.eye(4), 0.001, {"source_down": len(source), "target_down": len(target)}

    class O3d:
        """Open3D with its random seed recorded."""

        def __init__(self, o3d):
            self._o3d = o3d
            self.utility = type("Utility", (), {"random": type("Random", (), {"seed": staticmethod(seeds.append)}),
                                                "get_max_threads": staticmethod(o3d.utility.get_max_threads)})

        def __getattr__(self, name):
            return getattr(self._o3d, name)

    with tempfile.TemporaryDirectory() as tmp:
        cases, out = Path(tmp) / "cases", Path(tmp) / "timing.json"
        make_case(cases / "case_00000", box_surface(random.Random(3), 500), axis_angle((1, 2, 3), 120),
                  [0.1, -0.2, 2.8])
        real_import, saved = open3d_peers.import_open3d, (open3d_peers.import_open3d, open3d_peers.Pipeline)
        open3d_peers.import_open3d = lambda threads: O3d(real_import(threads))
        open3d_peers.Pipeline = probe_pipeline(run)
        try:
            args = open3d_peers.parse_args(["--timing", "--points", "256,300x200,600x700", "--repeats", "2",
                                            "--cases", str(cases), "--out", str(out), "--methods",
                                            "icp-p2p,fpfh-ransac-icp", "--seed", "5"])
            assert open3d_peers.timing(args) == 0
        finally:
            open3d_peers.import_open3d, open3d_peers.Pipeline = saved
        report = json.loads(out.read_text())
        got = [(r["method"], r["points"], r["observed_points"], r["source_down"], r["target_down"])
               for r in report["results"]]
        assert got == [("o3d-icp-p2p", 256, 256, 256, 256), ("o3d-fpfh-ransac-icp", 256, 256, 256, 256),
                       ("o3d-icp-p2p", 300, 200, 300, 200), ("o3d-fpfh-ransac-icp", 300, 200, 300, 200),
                       ("o3d-icp-p2p", 600, 700, 600, 700), ("o3d-fpfh-ransac-icp", 600, 700, 600, 700)], got
        assert len(calls) == 18, len(calls)  # a warm-up and 2 repeats per (size, method)
        o3d = open3d_peers.import_open3d(0)
        source_all = open3d_peers.read_points(o3d, cases / "case_00000" / "source.ply")
        target_all = open3d_peers.read_points(o3d, cases / "case_00000" / "target.ply")
        want_seeds = []
        for i, (label, m, n) in enumerate((("256", 256, 256), ("300x200", 300, 200), ("600x700", 600, 700))):
            rng = np.random.default_rng(peers_common.derived_seed(5, "timing", label))
            source = peers_common.resample(source_all, m, rng)
            target = peers_common.resample(target_all, n, rng)
            for _, s, t in calls[6 * i: 6 * i + 6]:
                assert s.shape == (m, 3) and t.shape == (n, 3), (label, s.shape, t.shape)
                assert np.array_equal(s, source) and np.array_equal(t, target), label
            for method in ("icp-p2p", "fpfh-ransac"):  # fpfh-ransac-icp seeds as fpfh-ransac
                want_seeds += [peers_common.derived_seed(5, "timing", label, method)] * 3
        assert seeds == want_seeds, (seeds, want_seeds)


def test_timing_pairs_time_the_first_k_cases_and_report_the_median_of_their_medians():
    """In this interpreter (numpy and Open3D needed): `--timing-pairs 2` on a set of three cases
    times the first two (the first with a one-pair run's draws, the second with its own), and
    the median is that of the two pairs' medians, not of all the runs pooled; a single case
    folder with --timing-pairs 2 is refused."""
    try:
        import numpy as np
        import open3d  # noqa: F401
    except ImportError as e:
        raise unittest.SkipTest(f"needs numpy and open3d: {e}")
    calls = []
    # Per call (a warm-up then 3 repeats per pair): pair 0 runs 1, 2, 9 (median 2), pair 1
    # runs 7, 8, 3 (median 7). Median of the medians 4.5; of the six runs pooled 5.
    seconds = [100.0, 1.0, 2.0, 9.0, 100.0, 7.0, 8.0, 3.0]

    def run(method, source, target):
        calls.append((np.array(source), np.array(target)))
        return np.eye(4), seconds[len(calls) - 1], {}

    with tempfile.TemporaryDirectory() as tmp:
        cases, out = Path(tmp) / "cases", Path(tmp) / "timing.json"
        for i in range(3):
            make_case(cases / f"case_{i:05d}", box_surface(random.Random(10 + i), 400), axis_angle((1, 2, 3), 40 * i),
                      [0.1, -0.2, 2.8])
        saved = open3d_peers.Pipeline
        open3d_peers.Pipeline = probe_pipeline(run)
        try:
            args = open3d_peers.parse_args(["--timing", "--points", "300x200", "--repeats", "3", "--cases",
                                            str(cases), "--timing-pairs", "2", "--out", str(out), "--methods",
                                            "icp-p2p", "--seed", "5"])
            assert open3d_peers.timing(args) == 0
            one = open3d_peers.parse_args(["--timing", "--points", "300x200", "--cases", str(cases / "case_00000"),
                                           "--timing-pairs", "2", "--out", str(out)])
            try:
                open3d_peers.timing(one)
                raise AssertionError("--timing-pairs 2 on one case folder was accepted")
            except SystemExit as e:
                assert "--timing-pairs must be 1" in str(e), e
        finally:
            open3d_peers.Pipeline = saved
        report = json.loads(out.read_text())
        assert report["pairs"] == 2, report["pairs"]
        (r,) = report["results"]
        assert r["pair_medians"] == [2.0, 7.0] and r["median_seconds"] == 4.5, r
        assert sorted(r["runs"]) == [1.0, 2.0, 3.0, 7.0, 8.0, 9.0], r
        assert len(calls) == 8, len(calls)
        o3d = open3d_peers.import_open3d(0)
        for i, first_call in ((0, 0), (1, 4)):
            case = cases / f"case_{i:05d}"
            rng = np.random.default_rng(peers_common.timing_pair_seed(5, "300x200", i))
            source = peers_common.resample(open3d_peers.read_points(o3d, case / "source.ply"), 300, rng)
            target = peers_common.resample(open3d_peers.read_points(o3d, case / "target.ply"), 200, rng)
            for s, t in calls[first_call:first_call + 4]:
                assert np.array_equal(s, source) and np.array_equal(t, target), i
        assert peers_common.timing_pair_seed(5, "300x200", 0) == peers_common.derived_seed(5, "timing", "300x200")


def run_tests():
    tests = [(name, fn) for name, fn in globals().items() if name.startswith("test_") and callable(fn)]
    failed = 0
    for name, fn in tests:
        try:
            fn()
            print(f"PASS {name}")
        except unittest.SkipTest as e:
            print(f"SKIP {name}: {e}")
        except Exception as e:  # noqa: BLE001
            failed += 1
            print(f"FAIL {name}: {type(e).__name__}: {e}")
    print(f"{len(tests) - failed} passed or skipped, {failed} failed")
    return 1 if failed else 0


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
    sys.exit(run_tests())

#!/usr/bin/env python3
"""Open3D registration peers for issue 7: ICP, FPFH + RANSAC (+ ICP) and FGR on exported cases.

Reads the case folders written by `cargo xtask export-cases` (source.ply = model points in the
model frame, target.ply = observed points in the camera frame, both in normalised object
units) and writes one JSON line per (case, method):

    {"case": "case_00000", "method": "o3d-fgr", "R": [[..],[..],[..]], "t": [x, y, z],
     "seconds": 0.012, "ok": true, "error": null}

with target ≈ R·source + t (the convention of gt.json). gt.json is never read. `seconds` is
the wall time of everything after reading the files: voxel down-sampling, normals, FPFH,
registration (each method does its own preprocessing, nothing is shared between methods).
A method that raises or returns a non-finite / non-rotation pose writes ok=false, R=t=null and
the message; the run goes on.

    open3d_peers.py --cases DIR --out results.jsonl [--methods ...] [--seed S] [--threads N]
    open3d_peers.py --check --cases DIR --out results.jsonl [--methods ...]
    open3d_peers.py --timing --points 512,1024x768,2048 --repeats 10 --out timing.json [--cases DIR [--timing-pairs K]]

See README.md next to this file for the parameters and why they were chosen.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

from peers_common import (cap_points, case_dirs, case_record, check_results, derived_seed, error_text, log,
                          machine_info, parse_sizes, record_failure, record_pose, resample, resume_done,
                          size_label, synthetic_pair, timing_cases, timing_pair_seed, timing_record, write_record,
                          write_report)

METHODS = ["icp-p2p", "icp-p2l", "fpfh-ransac", "fpfh-ransac-icp", "fgr"]
PREFIX = "o3d-"

# Voxel size v in normalised object units (the model spans [-1, 1] on its longest side).
# README.md explains the choice; every other length is the tutorial's multiple of v.
DEFAULT_VOXEL = 0.05


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description="Run Open3D registration methods on exported registration cases.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--cases", type=Path, help="folder of case folders (each with source.ply, target.ply)")
    p.add_argument("--out", type=Path, required=True, help="results.jsonl (run, --check) or timing.json (--timing)")
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of " + ",".join(METHODS))
    p.add_argument("--seed", type=int, default=0, help="seeds Open3D's RNG (per case and method) and the target cap")
    p.add_argument("--max-target-points", type=int, default=50000,
                   help="targets with more points are randomly subsampled to this many (room scenes), 0 = no cap")
    p.add_argument("--threads", type=int, default=0,
                   help="Open3D CPU threads (o3d.utility.set_max_threads); 0 = Open3D's default. "
                        "Use 1 for bit-repeatable RANSAC")
    p.add_argument("--voxel", type=float, default=DEFAULT_VOXEL, help="voxel size v in normalised object units")
    p.add_argument("--icp-distance", type=float, default=float("inf"),
                   help="max correspondence distance of icp-p2p / icp-p2l from identity (inf = vanilla ICP, every "
                        "nearest neighbour counts)")
    p.add_argument("--icp-max-iteration", type=int, default=30, help="ICP iterations (Open3D's default 30)")
    p.add_argument("--ransac-max-iteration", type=int, default=100000, help="RANSAC iterations (tutorial: 100000)")
    p.add_argument("--ransac-confidence", type=float, default=0.999, help="RANSAC confidence (tutorial: 0.999)")
    p.add_argument("--fgr-decrease-mu", action="store_true",
                   help="FGR with graduated non-convexity (decrease_mu=True, the C++ default); the Python binding "
                        "and so the tutorial default to False")
    p.add_argument("--fgr-absolute-scale", action="store_true",
                   help="FGR distance 0.5v in absolute units; by default (the tutorial) it is relative to the "
                        "clouds' normalised scale (use_absolute_scale=False)")
    p.add_argument("--limit", type=int, default=0, help="only the first N cases (0 = all)")
    p.add_argument("--resume", action="store_true",
                   help="keep the lines already in --out and run only the missing (case, method) pairs")
    p.add_argument("--details", action="store_true",
                   help="add a \"details\" object (fitness, inlier RMSE, point counts) to each line")
    p.add_argument("--check", action="store_true", help="validate --out: exactly one line per (case, method)")
    p.add_argument("--timing", action="store_true", help="timing mode on synthetic pairs, writes one JSON file")
    p.add_argument("--points", default="512,1024,2048",
                   help="timing mode: comma-separated sizes, each N (model and observed N points) or MxN "
                        "(model M, observed N)")
    p.add_argument("--repeats", type=int, default=5, help="timing mode: runs per (method, points), median reported")
    p.add_argument("--timing-pairs", type=int, default=1,
                   help="timing mode with a --cases set: time the first K cases, one warm-up and --repeats runs "
                        "each; the median of their medians is reported")
    args = p.parse_args(argv)
    args.methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in args.methods if m not in METHODS]
    if bad:
        p.error(f"unknown method(s) {bad}; choose from {METHODS}")
    if not args.timing and args.cases is None:
        p.error("--cases is required (except with --timing)")
    if not (args.voxel > 0 and math.isfinite(args.voxel)):
        p.error("--voxel must be positive")
    if args.threads < 0 or args.repeats < 1 or args.max_target_points < 0:
        p.error("--threads, --max-target-points must be >= 0 and --repeats >= 1")
    try:
        args.sizes = parse_sizes(args.points)
    except ValueError as e:
        p.error(f"--points: {e}")
    return args


def seed_key(method: str) -> str:
    """fpfh-ransac-icp refines the very pose fpfh-ransac returns (same seed, same RANSAC draws
    with one thread), so the two differ only by the refinement."""
    return "fpfh-ransac" if method == "fpfh-ransac-icp" else method


# ---------------------------------------------------------------------------------------------
# Open3D pipeline (imported lazily so that --check and --help work without Open3D)


def import_open3d(threads: int):
    if threads > 0:
        os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    import numpy as np  # noqa: F401
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    if threads > 0:
        o3d.utility.set_max_threads(threads)
    return o3d


class Pipeline:
    """The tutorial's parameters (global_registration.ipynb) as multiples of the voxel size v."""

    def __init__(self, o3d, args):
        import numpy as np

        self.o3d, self.np, self.reg = o3d, np, o3d.pipelines.registration
        v = args.voxel
        self.v = v
        self.normal_radius = 2.0 * v  # KDTreeSearchParamHybrid(radius=2v, max_nn=30)
        self.feature_radius = 5.0 * v  # KDTreeSearchParamHybrid(radius=5v, max_nn=100)
        self.ransac_distance = 1.5 * v  # "liberal" RANSAC distance threshold
        self.refine_distance = 0.4 * v  # point-to-plane ICP refinement after RANSAC
        self.fgr_distance = 0.5 * v  # FGR maximum_correspondence_distance
        self.icp_distance = args.icp_distance
        self.icp_criteria = self.reg.ICPConvergenceCriteria(max_iteration=args.icp_max_iteration)
        self.ransac_criteria = self.reg.RANSACConvergenceCriteria(args.ransac_max_iteration, args.ransac_confidence)
        self.details = args.details
        self.fgr_option = self.reg.FastGlobalRegistrationOption(
            maximum_correspondence_distance=self.fgr_distance, decrease_mu=args.fgr_decrease_mu,
            use_absolute_scale=args.fgr_absolute_scale)

    def config(self):
        return {
            "voxel": self.v, "normal_radius": self.normal_radius, "normal_max_nn": 30,
            "fpfh_radius": self.feature_radius, "fpfh_max_nn": 100,
            "ransac": {"distance": self.ransac_distance, "mutual_filter": True, "ransac_n": 3,
                       "checkers": {"edge_length": 0.9, "distance": self.ransac_distance},
                       "max_iteration": self.ransac_criteria.max_iteration,
                       "confidence": self.ransac_criteria.confidence,
                       "estimation": "point-to-point, no scaling"},
            "refine_icp": {"distance": self.refine_distance, "estimation": "point-to-plane",
                           "clouds": "full (capped) clouds, normals radius 2v"},
            "fgr": {"maximum_correspondence_distance": self.fgr_distance,
                    "use_absolute_scale": self.fgr_option.use_absolute_scale,
                    "decrease_mu": self.fgr_option.decrease_mu, "other": "Open3D defaults"},
            "icp_from_identity": {"distance": self.icp_distance if math.isfinite(self.icp_distance) else "inf",
                                  "max_iteration": self.icp_criteria.max_iteration,
                                  "clouds": "full (capped) clouds, p2l target normals radius 2v"},
        }

    def cloud(self, points):
        pc = self.o3d.geometry.PointCloud()
        pc.points = self.o3d.utility.Vector3dVector(points)
        return pc

    def normals(self, pc):
        pc.estimate_normals(self.o3d.geometry.KDTreeSearchParamHybrid(radius=self.normal_radius, max_nn=30))

    def preprocess(self, pc):
        down = pc.voxel_down_sample(self.v)
        self.normals(down)
        fpfh = self.reg.compute_fpfh_feature(
            down, self.o3d.geometry.KDTreeSearchParamHybrid(radius=self.feature_radius, max_nn=100))
        return down, fpfh

    def icp(self, src, tgt, distance, init, point_to_plane):
        est = (self.reg.TransformationEstimationPointToPlane() if point_to_plane
               else self.reg.TransformationEstimationPointToPoint())
        return self.reg.registration_icp(src, tgt, distance, init, est, self.icp_criteria)

    def ransac(self, sd, td, sf, tf):
        d = self.ransac_distance
        return self.reg.registration_ransac_based_on_feature_matching(
            sd, td, sf, tf, True, d, self.reg.TransformationEstimationPointToPoint(False), 3,
            [self.reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), self.reg.CorrespondenceCheckerBasedOnDistance(d)],
            self.ransac_criteria)

    def run(self, method, source_pts, target_pts):
        """Runs one method from raw points; returns (4x4 transform, seconds, details)."""
        np = self.np
        src, tgt = self.cloud(source_pts), self.cloud(target_pts)
        details = {}
        t0 = time.perf_counter()
        if method in ("icp-p2p", "icp-p2l"):
            p2l = method == "icp-p2l"
            if p2l:
                self.normals(tgt)
            res = self.icp(src, tgt, self.icp_distance, np.eye(4), p2l)
        else:
            sd, sf = self.preprocess(src)
            td, tf = self.preprocess(tgt)
            if method == "fgr":
                res = self.reg.registration_fgr_based_on_feature_matching(sd, td, sf, tf, self.fgr_option)
            else:
                res = self.ransac(sd, td, sf, tf)
                if method == "fpfh-ransac-icp":
                    if self.details:
                        details["ransac_fitness"] = res.fitness
                    self.normals(tgt)
                    res = self.icp(src, tgt, self.refine_distance, res.transformation, True)
            details.update(source_down=len(sd.points), target_down=len(td.points))
        seconds = time.perf_counter() - t0
        details.update(fitness=res.fitness, inlier_rmse=res.inlier_rmse,
                       correspondences=len(res.correspondence_set))
        return np.asarray(res.transformation).copy(), seconds, details


def read_points(o3d, path: Path):
    import numpy as np

    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing")
    pts = np.asarray(o3d.io.read_point_cloud(str(path), format="ply").points).copy()
    if pts.ndim != 2 or pts.shape[0] == 0:
        raise ValueError(f"{path}: no points read")
    if not np.isfinite(pts).all():
        raise ValueError(f"{path}: non-finite coordinates")
    return pts


# ---------------------------------------------------------------------------------------------
# Modes


def run_cases(args):
    o3d = import_open3d(args.threads)
    pipe = Pipeline(o3d, args)
    dirs = case_dirs(args.cases)
    if args.limit:
        dirs = dirs[: args.limit]
    config = {"cases": str(args.cases), "out": str(args.out), "methods": [PREFIX + m for m in args.methods],
              "seed": args.seed, "max_target_points": args.max_target_points,
              "threads": args.threads or "open3d default", "open3d_max_threads": o3d.utility.get_max_threads(),
              "open3d": o3d.__version__, "case_count": len(dirs), **pipe.config()}
    print(f"open3d_peers seed {args.seed} config {json.dumps(config)}", flush=True)

    done = resume_done(args.out, args.resume)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    total = len(dirs) * len(args.methods)
    n = failures = 0
    started = time.perf_counter()
    with open(args.out, "a" if args.resume else "w") as out:
        for d in dirs:
            name = d.name
            pending = [m for m in args.methods if (name, PREFIX + m) not in done]
            n += len(args.methods) - len(pending)
            if not pending:
                continue
            try:
                source = read_points(o3d, d / "source.ply")
                target = cap_points(read_points(o3d, d / "target.ply"), args.max_target_points,
                                    derived_seed(args.seed, name, "cap"))
                load_error = None
            except Exception as e:  # noqa: BLE001 - a broken case must not stop the run
                load_error = error_text(e)
            for m in pending:
                n += 1
                rec = case_record(name, PREFIX + m, load_error)
                if load_error is None:
                    try:
                        o3d.utility.random.seed(derived_seed(args.seed, name, seed_key(m)))
                        T, seconds, details = pipe.run(m, source, target)
                        record_pose(rec, T, seconds)
                        if args.details:
                            rec["details"] = {"source_points": len(source), "target_points": len(target), **details}
                    except Exception as e:  # noqa: BLE001
                        record_failure(rec, e)
                failures += write_record(out, rec, n, total)
    log(f"done: {total} results, {failures} failed, {time.perf_counter() - started:.1f}s, wrote {args.out}")
    return 0


def check(args):
    """One well-formed line per (case, method); prints the problems, returns 1 if any."""
    return check_results(args.out, args.cases, args.limit, [PREFIX + m for m in args.methods])


def timing(args):
    import numpy as np

    o3d = import_open3d(args.threads)
    pipe = Pipeline(o3d, args)
    cases = timing_cases(args.cases, args.timing_pairs)
    pair = ", ".join(str(c) for c in cases) if cases else "synthetic bumpy ellipsoid"
    config = {"mode": "timing", "points": [size_label(*size) for size in args.sizes], "repeats": args.repeats,
              "seed": args.seed, "methods": [PREFIX + m for m in args.methods],
              "threads": args.threads or "open3d default", "pairs": max(len(cases), 1),
              "pair": pair, **pipe.config()}
    print(f"open3d_peers seed {args.seed} config {json.dumps(config)}", flush=True)
    clouds = [(read_points(o3d, c / "source.ply"), read_points(o3d, c / "target.ply")) for c in cases]
    results = []
    total, k = len(args.sizes) * len(args.methods), 0
    for n_model, n_obs in args.sizes:
        # The seeds' key: str(n) for a square size (the draws of plain `--points N`), else "MxN".
        size = size_label(n_model, n_obs)
        if not cases:
            pairs = [synthetic_pair(n_model, derived_seed(args.seed, "timing"), observed=n_obs)]
        else:
            pairs = []
            for i, (source_all, target_all) in enumerate(clouds):
                rng = np.random.default_rng(timing_pair_seed(args.seed, size, i))
                pairs.append((resample(source_all, n_model, rng), resample(target_all, n_obs, rng)))
        for m in args.methods:
            k += 1
            pair_runs, details, error = [], {}, None
            try:
                for source, target in pairs:
                    runs = []
                    o3d.utility.random.seed(derived_seed(args.seed, "timing", size, seed_key(m)))
                    pipe.run(m, source, target)  # warm-up, not counted
                    for _ in range(args.repeats):
                        o3d.utility.random.seed(derived_seed(args.seed, "timing", size, seed_key(m)))
                        _, seconds, details = pipe.run(m, source, target)
                        runs.append(seconds)
                    pair_runs.append(runs)
            except Exception as e:  # noqa: BLE001
                error = error_text(e)
                pair_runs = []
            runs = [s for r in pair_runs for s in r]
            results.append(timing_record(PREFIX + m, n_model, n_obs, runs, error, k, total,
                                         pair_runs=pair_runs if len(pairs) > 1 else None,
                                         source_down=details.get("source_down"),
                                         target_down=details.get("target_down")))
    report = {"machine": machine_info(o3d.utility.get_max_threads()), "open3d_version": o3d.__version__,
              "threads": args.threads or o3d.utility.get_max_threads(), "seed": args.seed,
              "repeats": args.repeats, "pairs": config["pairs"], "pair": config["pair"], "config": pipe.config(),
              "results": results}
    write_report(args.out, report)
    return 0


def main(argv=None):
    args = parse_args(argv)
    if args.check:
        return check(args)
    if args.timing:
        return timing(args)
    return run_cases(args)


if __name__ == "__main__":
    sys.exit(main())

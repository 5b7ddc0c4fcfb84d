#!/usr/bin/env python3
"""Chooses ppf-tuned's parameters on *validation* cases (README.md, "Tuning").

    tune_ppf.py --cases target/ppf-val-noback --out target/ppf-tune/sweep.jsonl \
        --stage 'sample:' --stage 'coarse:rel_sampling=0.04,scene_step=1/5' \
        --refine 'none:' --refine 'icp:icp=true' --refine 'fit5:icp=true,hypotheses=5,select=fit'

Each --stage is a NAME:OVERRIDES of the PPF stage (normals, training, matching) on OpenCV's
sample parameters; each --refine is a NAME:OVERRIDES of what follows it (ICP, hypotheses,
selection). Every stage runs once per case and every refinement on its poses, so a grid of
refinements costs little. One JSON line per (stage, refinement, case) with the rotation and
translation errors against gt.json and the times, then a table per (stage, refinement):
accuracy at 5/10/15°, median rotation error, median seconds (PPF stage + refinement).

It reads gt.json, so it refuses case folders whose manifest.json says they come from the test
split: tune on cases exported with `--split train` only. `--resume` keeps the lines in --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
import time
from pathlib import Path

import ppf_peers as pp
from peers_common import case_dirs, derived_seed, error_text, log, read_jsonl


def named(spec: str):
    name, sep, overrides = spec.partition(":")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"{spec!r}: expected NAME:OVERRIDES (OVERRIDES may be empty)")
    return name, overrides


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--cases", type=Path, required=True, help="validation case folders (train-split objects)")
    p.add_argument("--out", type=Path, required=True, help="sweep.jsonl")
    p.add_argument("--stage", type=named, action="append", required=True, help="NAME:OVERRIDES of the PPF stage")
    p.add_argument("--refine", type=named, action="append", required=True, help="NAME:OVERRIDES of the refinement")
    p.add_argument("--limit", type=int, default=20, help="the first N cases (0 = all)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--objects", type=Path, help="mesh folder (default: from the cases' manifest.json)")
    p.add_argument("--resume", action="store_true", help="keep the lines already in --out")
    p.add_argument("--summarise", action="store_true", help="only print the table of the lines in --out")
    args = p.parse_args(argv)
    args.model_normals = "mesh"
    try:
        args.stages = [(n, pp.override(pp.SAMPLE, o)) for n, o in args.stage]
        args.refines = [(n, o) for n, o in args.refine]
        for _, stage in args.stages:
            for _, o in args.refines:
                pp.override(stage, o)
    except ValueError as e:
        p.error(str(e))
    return args


def split_of(cases: Path):
    f = cases / "manifest.json"
    if not f.is_file():
        raise SystemExit(f"{f} is missing: cannot tell which split the cases come from")
    return (json.loads(f.read_text()).get("config") or {}).get("split")


def rotation_error_deg(R, G):
    import numpy as np

    c = (np.trace(R.T @ G) - 1) / 2
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def main(argv=None):
    import numpy as np

    args = parse_args(argv)
    if args.summarise:
        summarise(args.out, [n for n, _ in args.stages], [n for n, _ in args.refines])
        return 0
    split = split_of(args.cases)
    if split != "train":
        raise SystemExit(f"{args.cases}/manifest.json says split {split!r}: tune on cases of the train split only "
                         "(cargo xtask export-cases --split train)")
    cv2 = pp.import_cv2(args.threads)
    ppf = pp.Ppf(cv2)
    normals_of = pp.ModelNormals(args)
    dirs = case_dirs(args.cases)[: args.limit or None]
    done = set()
    if args.resume and args.out.exists():
        done = {(r["stage"], r["refine"], r["case"]) for r in read_jsonl(args.out) if "stage" in r}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "a" if args.resume else "w") as out:
        for sname, stage_params in args.stages:
            for d in dirs:
                todo = [(rn, ro) for rn, ro in args.refines if (sname, rn, d.name) not in done]
                if not todo:
                    continue
                gt = json.loads((d / "gt.json").read_text())
                G, g = np.array(gt["R"]), np.array(gt["t"])
                source = pp.read_points(d / "source.ply")
                target = pp.read_points(d / "target.ply")
                normals, _ = normals_of(d, source)
                model = np.hstack([source, normals]).astype(np.float32)
                cv2.setRNGSeed(derived_seed(args.seed, d.name, "tune"))
                try:
                    stage, stage_error = ppf.detect(stage_params, model, target), None
                except Exception as e:  # noqa: BLE001
                    stage, stage_error = None, error_text(e)
                for rname, ro in todo:
                    params = pp.override(stage_params, ro)
                    rec = {"stage": sname, "refine": rname, "case": d.name, "params": dataclasses.asdict(params)}
                    if stage is None:
                        rec.update(ok=False, error=stage_error, rot=180.0, trans=math.inf, seconds=None)
                    else:
                        t0 = time.perf_counter()
                        try:
                            T, seconds, details, _ = ppf.run(params, model, target, stage)
                            rec.update(ok=True, error=None, rot=rotation_error_deg(T[:3, :3], G),
                                       trans=float(np.linalg.norm(T[:3, 3] - g)), seconds=seconds,
                                       ppf_seconds=stage.seconds, votes=stage.votes[:3])
                        except Exception as e:  # noqa: BLE001
                            rec.update(ok=False, error=error_text(e), rot=180.0, trans=math.inf,
                                       seconds=stage.seconds + time.perf_counter() - t0)
                    out.write(json.dumps(rec) + "\n")
                    out.flush()
                log(f"{sname} {d.name} ppf {stage.seconds if stage else 0:.2f}s "
                    + " ".join(f"{rn}" for rn, _ in todo))
    summarise(args.out, [n for n, _ in args.stages], [n for n, _ in args.refines])
    return 0


def summarise(path: Path, stages, refines):
    last = {}  # the last line of each (stage, refinement, case)
    for r in read_jsonl(path):
        if "stage" in r and r["stage"] in stages and r["refine"] in refines:
            last[(r["stage"], r["refine"], r["case"])] = r
    rows = {}
    for (s, f, _), r in last.items():
        rows.setdefault((s, f), []).append(r)
    print(f"{'stage':14s} {'refine':12s} {'n':>3s} {'<5°':>5s} {'<10°':>5s} {'<15°':>5s} {'med°':>7s} {'med s':>7s}")
    for s in stages:
        for f in refines:
            v = rows.get((s, f), [])
            if not v:
                continue
            rot = [r["rot"] for r in v]
            secs = [r["seconds"] for r in v if r["seconds"] is not None]
            acc = [sum(e < t for e in rot) / len(rot) for t in (5, 10, 15)]
            print(f"{s:14s} {f:12s} {len(v):3d} {acc[0]:5.2f} {acc[1]:5.2f} {acc[2]:5.2f} "
                  f"{statistics.median(rot):7.1f} {statistics.median(secs) if secs else math.nan:7.2f}")


if __name__ == "__main__":
    sys.exit(main())

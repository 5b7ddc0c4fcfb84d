"""Helpers shared by the peers' scripts (open3d_peers.py, ppf_peers.py; see README.md).

Case folders, derived seeds, the target cap, the result lines and their `--check`, the timing
sizes (`--points`) and pairs and the machine description. Standard library at import time; numpy is imported inside
the functions that need it, so `--check` and `--help` work without it.
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
import sys
import zlib
from pathlib import Path

RESULT_KEYS = ("case", "method", "R", "t", "seconds", "ok", "error")


def log(msg):
    print(msg, file=sys.stderr, flush=True)


def case_dirs(root: Path):
    if not root.is_dir():
        raise SystemExit(f"--cases {root}: not a folder")
    dirs = sorted(d for d in root.iterdir() if d.is_dir())
    if not dirs:
        raise SystemExit(f"--cases {root}: no case folders")
    return dirs


def derived_seed(seed: int, *parts: str) -> int:
    """A seed that depends only on (seed, parts): results do not depend on what ran before."""
    h = zlib.crc32("\x1f".join(parts).encode())
    return (seed * 1_000_003 + h) % (2**31 - 1)


def parse_sizes(text: str) -> list[tuple[int, int]]:
    """The timing sizes of `--points`: comma-separated entries, each `N` (model and observed
    both N points) or `MxN` (model M points, observed N), positive integers; as (M, N) pairs in
    the order given. Empty entries are skipped; a bad entry, or none at all, raises ValueError
    naming it."""
    sizes = []
    for entry in text.split(","):
        if not entry.strip():
            continue
        parts = [x.strip() for x in entry.lower().split("x")]
        if len(parts) > 2 or not all(re.fullmatch(r"[0-9]+", x) for x in parts) or min(map(int, parts)) < 1:
            raise ValueError(f"bad size {entry.strip()!r}: expected N or MxN (model x observed points), "
                             "positive integers")
        m, n = int(parts[0]), int(parts[-1])
        sizes.append((m, n))
    if not sizes:
        raise ValueError(f"{text!r}: no sizes (expected comma-separated N or MxN)")
    return sizes


def size_label(m: int, n: int) -> str:
    """How a timing size is written (log lines, config, seed keys): `N` when square, else `MxN`."""
    return str(m) if m == n else f"{m}x{n}"


def cap_points(pts, max_points: int, seed: int):
    """At most `max_points` of `pts`: a uniform random subset without replacement, in file order."""
    import numpy as np

    if max_points <= 0 or len(pts) <= max_points:
        return pts
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(len(pts), size=max_points, replace=False))
    return pts[idx]


def pose_fields(T):
    """(R rows, t) of a 4×4 transform as plain floats; raises unless it is a finite rotation."""
    import numpy as np

    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    if not (np.isfinite(T).all() and np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0):
        raise ValueError(f"not a rigid transform: {T.tolist()}")
    return [[float(x) for x in row] for row in R], [float(x) for x in t]


def error_text(e: BaseException) -> str:
    msg = f"{type(e).__name__}: {e}".strip()
    # Open3D errors carry ANSI colour codes.
    for code in ("\x1b[1;31m", "\x1b[0;m", "\x1b[0m"):
        msg = msg.replace(code, "")
    return msg


def machine_info(threads_used):
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "logical_cpus": os.cpu_count(), "system": platform.platform(),
            "python": platform.python_version(), "threads_used": threads_used}


def read_jsonl(path: Path):
    recs = []
    with open(path) as f:
        for i, line in enumerate(f, 1):
            if line.strip():
                try:
                    recs.append(json.loads(line))
                except json.JSONDecodeError as e:
                    recs.append({"_bad_line": i, "_error": str(e)})
    return recs


def check_results(out: Path, cases: Path, limit: int, methods) -> int:
    """Exactly one well-formed line per (case, method) of the first `limit` cases (0 = all) and
    the full method names `methods`; prints the problems, returns 1 if any."""
    problems = []
    if not out.is_file():
        print(f"check: {out} does not exist")
        return 1
    recs = read_jsonl(out)
    expected = {(d.name, m) for d in case_dirs(cases)[: limit or None] for m in methods}
    seen = {}
    for i, r in enumerate(recs, 1):
        if "_bad_line" in r:
            problems.append(f"line {r['_bad_line']}: not JSON ({r['_error']})")
            continue
        key = (r.get("case"), r.get("method"))
        seen[key] = seen.get(key, 0) + 1
        missing = [k for k in RESULT_KEYS if k not in r]
        if missing:
            problems.append(f"line {i} {key}: missing keys {missing}")
            continue
        if r["ok"]:
            R, t = r["R"], r["t"]
            good = (isinstance(R, list) and len(R) == 3 and all(isinstance(row, list) and len(row) == 3 for row in R)
                    and isinstance(t, list) and len(t) == 3
                    and all(isinstance(x, (int, float)) and math.isfinite(x) for x in sum(R, []) + t))
            if not good:
                problems.append(f"line {i} {key}: ok but R/t malformed")
            elif r["error"] is not None:
                problems.append(f"line {i} {key}: ok but error is set")
        elif not isinstance(r["error"], str):
            problems.append(f"line {i} {key}: not ok and no error message")
        if not (isinstance(r["seconds"], (int, float)) and r["seconds"] >= 0):
            problems.append(f"line {i} {key}: bad seconds {r['seconds']!r}")
    for key in sorted(expected - seen.keys()):
        problems.append(f"missing {key}")
    for key, count in sorted(seen.items(), key=str):
        if count > 1:
            problems.append(f"{count} lines for {key}")
        if key not in expected:
            problems.append(f"unexpected {key}")
    ok = sum(1 for r in recs if r.get("ok") is True)
    for p in problems[:50]:
        print("check:", p)
    if len(problems) > 50:
        print(f"check: … {len(problems) - 50} more")
    print(f"check: {len(recs)} lines, {len(expected)} expected, {ok} ok, {len(recs) - ok} failed, "
          f"{len(problems)} problems -> {'PASS' if not problems else 'FAIL'}")
    return 0 if not problems else 1


def resume_done(out: Path, resume: bool):
    """The (case, method) pairs already in `out` when resuming; else none."""
    if resume and out.exists():
        return {(r.get("case"), r.get("method")) for r in read_jsonl(out)}
    return set()


def case_record(name: str, method: str, error):
    """A result line that has not (yet) succeeded: `error` is why (None until a method runs)."""
    return {"case": name, "method": method, "R": None, "t": None, "seconds": 0.0, "ok": False, "error": error}


def record_pose(rec, T, seconds):
    """Fills `rec` with the pose `T` found in `seconds` (raises, as pose_fields, on a bad one)."""
    rec["seconds"] = seconds
    rec["R"], rec["t"] = pose_fields(T)
    rec["ok"], rec["error"] = True, None


def record_failure(rec, e: BaseException):
    rec["R"] = rec["t"] = None
    rec["ok"], rec["error"] = False, error_text(e)


def write_record(out, rec, n: int, total: int) -> bool:
    """Writes `rec` as the `n`-th of `total` lines and logs it; whether it failed."""
    out.write(json.dumps(rec) + "\n")
    out.flush()
    status = "ok" if rec["ok"] else f"FAILED: {rec['error']}"
    log(f"[{n}/{total}] {rec['case']} {rec['method']} {rec['seconds']:.3f}s {status}")
    return not rec["ok"]


def timing_cases(cases: Path | None, pairs: int) -> list[Path]:
    """The case folders timed: `cases` itself when it is one case (a folder with source.ply;
    then `pairs` must be 1), else the first `pairs` case folders of the set `cases` (fewer when
    the set is smaller); none without `--cases` (a synthetic pair)."""
    if pairs < 1:
        raise SystemExit(f"--timing-pairs {pairs}: must be at least 1")
    if cases is None:
        return []
    if (cases / "source.ply").is_file():
        if pairs != 1:
            raise SystemExit(f"--cases {cases} is one case: --timing-pairs must be 1, not {pairs}")
        return [cases]
    return case_dirs(cases)[:pairs]


def timing_pair_seed(seed: int, size: str, index: int) -> int:
    """The resampling seed of the `index`-th timed pair at `size` (the first pair keeps the
    seed of a one-pair run, so its numbers do not change)."""
    if index == 0:
        return derived_seed(seed, "timing", size)
    return derived_seed(seed, "timing", size, f"pair{index}")


def timing_record(method: str, m: int, n: int, runs, error, k: int, total: int, pair_runs=None, **extra):
    """One timing result (method at `m` model and `n` observed points: the seconds of each
    repeat, or the error), logged as the `k`-th of `total`; `extra` are the script's own fields.

    With `pair_runs` (one list of repeats per timed pair; `runs` is then all of them), the
    median is the median of the pairs' medians: every pair counts once, however its repeats
    spread."""
    import statistics

    pair_medians = [statistics.median(r) for r in pair_runs if r] if pair_runs else None
    median = statistics.median(pair_medians) if pair_medians else (statistics.median(runs) if runs else None)
    rec = {"method": method, "points": m, "observed_points": n,
           "median_seconds": median if runs else None,
           "min_seconds": min(runs) if runs else None, "runs": runs, "ok": error is None, "error": error,
           **extra}
    if pair_medians is not None:
        rec["pair_medians"] = pair_medians
    med = f"{rec['median_seconds']:.4f}s" if runs else f"FAILED: {error}"
    log(f"[{k}/{total}] {method} n={size_label(m, n)} median {med}")
    return rec


def write_report(out: Path, report):
    """Writes the timing `report` to `out` (through a temporary file) and logs it."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(report, indent=2) + "\n")
    tmp.replace(out)
    log(f"wrote {out}")


def synthetic_pair(n: int, seed: int, with_normals: bool = False, observed: int | None = None):
    """n model points on a bumpy closed surface spanning [-1, 1], and `observed` (default n)
    points of an independent sample of the same surface rotated and moved to z = 2.8 with 0.005
    noise. The surface and the pose depend on the seed only, the samples on (seed, n) when
    square (observed = n) and on (seed, n, observed) otherwise.

    With `with_normals`, also the model's outward unit normals (the gradient of the surface's
    implicit function |x/s| − r(x/s / |x/s|), by central differences): (model, normals, target).
    The random draws are the same either way."""
    import numpy as np

    rng = np.random.default_rng(seed)
    freqs = rng.normal(size=(6, 3)) * 2.0
    phases = rng.uniform(0, 2 * np.pi, 6)
    amps = rng.uniform(0.05, 0.2, 6)
    stretch = np.array([1.0, 0.7, 0.45])

    def radius(d):
        return 1.0 + (amps * np.sin(d @ freqs.T + phases)).sum(axis=1)

    def sample(k):
        d = rng.normal(size=(k, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d * radius(d)[:, None] * stretch

    def implicit(x):
        u = x / stretch
        r = np.linalg.norm(u, axis=1)
        return r - radius(u / r[:, None])

    q = rng.normal(size=4)
    n_obs = n if observed is None else observed
    rng = np.random.default_rng([seed, n] if n_obs == n else [seed, n, n_obs])
    model, observed = sample(n), sample(n_obs)
    normals = None
    if with_normals:
        h = 1e-6
        grad = np.stack([(implicit(model + h * e) - implicit(model - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
        normals = grad / np.linalg.norm(grad, axis=1, keepdims=True)
    lo, hi = model.min(0), model.max(0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    model, observed = (model - centre) / half, (observed - centre) / half
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    target = observed @ R.T + np.array([0.0, 0.0, 2.8]) + rng.normal(scale=0.005, size=observed.shape)
    if with_normals:
        return model, normals, target
    return model, target


def resample_indices(count: int, n: int, rng):
    """Which of `count` points make an n-point resample, and the jitter added to each:
    a random subset in file order when count ≥ n, else every point plus random repeats
    jittered by N(0, 0.005²) per coordinate. `pts[idx] + jitter` is `resample(pts, n, rng)`."""
    import numpy as np

    if count >= n:
        return np.sort(rng.choice(count, size=n, replace=False)), np.zeros((n, 3))
    extra = rng.choice(count, size=n - count)
    jitter = rng.normal(scale=0.005, size=(n - count, 3))
    return np.concatenate([np.arange(count), extra]), np.concatenate([np.zeros((count, 3)), jitter])


def resample(pts, n, rng):
    """Exactly n points of `pts` (see resample_indices)."""
    idx, jitter = resample_indices(len(pts), n, rng)
    return pts[idx] + jitter

#!/usr/bin/env python3
"""OpenCV point-pair-feature peers: Drost et al. 2010 (`cv2.ppf_match_3d.PPF3DDetector`), alone,
refined by OpenCV's ICP, and a variant tuned on validation cases, on exported cases.

Reads the case folders written by `cargo xtask export-cases` (source.ply = model points in the
model frame, target.ply = observed points in the camera frame, both in normalised object units,
the camera at the origin looking down +z) and writes one JSON line per (case, method) in the
format of open3d_peers.py and our CLI:

    {"case": "case_00000", "method": "opencv-ppf", "R": [[..],[..],[..]], "t": [x, y, z],
     "seconds": 12.3, "ok": true, "error": null}

with target ≈ R·source + t (the convention of gt.json). gt.json is never read.

PPF needs normals. The model's come from the object's mesh (the face each source point lies on,
outward); the scene's are estimated on target.ply (plane fit within 2 voxels, oriented toward
the camera). `seconds` is the wall time of everything after reading the files and the mesh:
the scene normals, training the detector on the model (it changes with every case), matching,
and ICP for the refined methods.

    ppf_peers.py --cases DIR --out results.jsonl [--methods ...] [--seed S] [--threads N]
    ppf_peers.py --check --cases DIR --out results.jsonl [--methods ...]
    ppf_peers.py --timing --points 512,1024x768,2048 --repeats 3 --out timing.json [--cases DIR]

See README.md next to this file for every parameter and why.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

from peers_common import (cap_points, case_dirs, case_record, check_results, derived_seed, error_text, log,
                          machine_info, parse_sizes, record_failure, record_pose, resample_indices, resume_done,
                          size_label, synthetic_pair, timing_record, write_record, write_report)

METHODS = ["ppf", "ppf-icp", "ppf-tuned"]
PREFIX = "opencv-"

# The voxel of our observed clouds: the paper's 0.05·√2/2 normalised units
# (ic_data::PAPER_VOXEL_SIZE; the object's longest side is 2 units).
DATA_VOXEL = 0.05 * math.sqrt(0.5)

# A source point farther than this from the mesh means the mesh is not the one the case was
# sampled from (another folder, or a scale-augmented export).
MESH_TOLERANCE = 1e-3

MESH_EXTENSIONS = (".obj", ".ply", ".off")


@dataclasses.dataclass(frozen=True)
class PpfParams:
    """One method's parameters. The first five are OpenCV's own (relative to the bounding box of
    the model or the scene, see README.md); lengths are normalised object units."""

    rel_sampling: float = 0.025  # PPF3DDetector relativeSamplingStep
    rel_distance: float = 0.05  # PPF3DDetector relativeDistanceStep
    num_angles: int = 30  # PPF3DDetector numAngles (OpenCV's default)
    scene_step: float = 1.0 / 40.0  # match relativeSceneSampleStep
    scene_distance: float = 0.05  # match relativeSceneDistance
    normal_radius: float = 2.0 * DATA_VOXEL  # scene normals: plane fit over the points within it
    icp: bool = False  # refine with cv2.ppf_match_3d_ICP
    icp_iterations: int = 100
    icp_tolerance: float = 0.005
    icp_rejection_scale: float = 2.5
    icp_levels: int = 0  # 0: as many as keep the sample's coarsest level (52 points), see icp_pyramid
    hypotheses: int = 1  # ICP refines this many of PPF's poses (most votes first)
    select: str = "votes"  # "votes": the first of them; "fit": the refined pose that fits best
    fit_distance: float = 2.0 * DATA_VOXEL  # "fit": model points within this of a scene point

    def ppf_key(self):
        """The parameters of the PPF stage (before ICP): methods that share them share it."""
        return (self.rel_sampling, self.rel_distance, self.num_angles, self.scene_step,
                self.scene_distance, self.normal_radius)


# OpenCV's sample (samples/python/ppf_load_match.py and samples/ppf_load_match.cpp):
# PPF3DDetector(0.025, 0.05), match(scene, 1.0/40.0, 0.05), ICP(100, 0.005, 2.5, 8). The ICP's
# 8 pyramid levels are for the sample's 6700-point model; ours adapt (icp_pyramid).
SAMPLE = PpfParams()

# The sample's model has 6700 points and its ICP 8 levels, each halving the model: its coarsest
# level registers 6700 / 2^7 ≈ 52 points. OpenCV's ICP needs that many: with our 1024-point
# models and 8 levels the coarsest has 8 points and the ICP diverges even from the true pose.
SAMPLE_COARSEST_POINTS = 6700 / 2**7


def icp_pyramid(levels: int, model_points: int) -> int:
    """The ICP's pyramid levels: `levels`, or with 0 as many as keep the sample's coarsest
    level of about 52 model points (5 for 1024 points, 4 for 512, 6 for 2048)."""
    if levels > 0:
        return levels
    return max(1, 1 + int(math.floor(math.log2(max(model_points, 1) / SAMPLE_COARSEST_POINTS))))

# Chosen on validation cases of the blob *train* objects only (README.md, "Tuning ppf-tuned"):
# a coarser model (faster training, the time's bulk), more scene reference points, finer angle
# bins, and ICP from the ten best poses keeping the one that fits the scene best.
TUNED = PpfParams(rel_sampling=0.05, num_angles=45, scene_step=1.0 / 2.0, scene_distance=0.03, icp=True,
                  icp_levels=3, hypotheses=10, select="fit")

PARAMS = {
    "ppf": SAMPLE,
    "ppf-icp": dataclasses.replace(SAMPLE, icp=True),
    "ppf-tuned": TUNED,
}


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description="Run OpenCV's point-pair-feature matcher (Drost et al. 2010) on exported registration cases.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--cases", type=Path,
                   help="folder of case folders (each with source.ply, target.ply, meta.json), or with --timing "
                        "one case folder or such a folder")
    p.add_argument("--out", type=Path, required=True, help="results.jsonl (run, --check) or timing.json (--timing)")
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of " + ",".join(METHODS))
    p.add_argument("--seed", type=int, default=0,
                   help="seeds OpenCV's RNG (per case and method), the target cap and the timing pairs")
    p.add_argument("--threads", type=int, default=0,
                   help="cv2.setNumThreads(N); 0 = OpenCV's default. The PyPI wheel's PPF and ICP loops are "
                        "single-threaded whatever N (README.md)")
    p.add_argument("--max-target-points", type=int, default=50000,
                   help="targets with more points are randomly subsampled to this many (room scenes), 0 = no cap")
    p.add_argument("--objects", type=Path,
                   help="folder of the meshes the cases were exported from (<object_id>.obj|ply|off); default: the "
                        "folder named in the cases' manifest.json. A case's own model.ply is used first")
    p.add_argument("--model-normals", choices=["mesh", "estimate"], default="mesh",
                   help="mesh: the normal of the mesh face each source point lies on, outward (the default); "
                        "estimate: a plane fit on source.ply oriented away from its centroid, for objects without "
                        "a mesh file (procedural objects); only right for star-shaped objects")
    p.add_argument("--tuned", default="",
                   help="override ppf-tuned's parameters, e.g. 'scene_step=0.1,hypotheses=3' (for tuning on "
                        "validation cases; the fields of PpfParams)")
    p.add_argument("--limit", type=int, default=0, help="only the first N cases (0 = all)")
    p.add_argument("--resume", action="store_true",
                   help="keep the lines already in --out and run only the missing (case, method) pairs")
    p.add_argument("--details", action="store_true",
                   help="add a \"details\" object (stage times, point counts, votes, fit) to each line")
    p.add_argument("--check", action="store_true", help="validate --out: exactly one line per (case, method)")
    p.add_argument("--timing", action="store_true", help="timing mode, writes one JSON file")
    p.add_argument("--points", default="512,1024,2048",
                   help="timing mode: comma-separated sizes, each N (model and observed N points) or MxN "
                        "(model M, observed N)")
    p.add_argument("--repeats", type=int, default=3, help="timing mode: runs per (method, points), median reported")
    args = p.parse_args(argv)
    args.methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in args.methods if m not in METHODS]
    if bad:
        p.error(f"unknown method(s) {bad}; choose from {METHODS}")
    if not args.methods:
        p.error("--methods is empty")
    if not args.timing and args.cases is None:
        p.error("--cases is required (except with --timing)")
    if args.threads < 0 or args.repeats < 1 or args.max_target_points < 0 or args.limit < 0:
        p.error("--threads, --max-target-points and --limit must be >= 0 and --repeats >= 1")
    try:
        args.sizes = parse_sizes(args.points)
    except ValueError as e:
        p.error(f"--points: {e}")
    try:
        args.params = dict(PARAMS, **{"ppf-tuned": override(TUNED, args.tuned)})
    except ValueError as e:
        p.error(f"--tuned: {e}")
    if args.objects is not None and not args.objects.is_dir():
        p.error(f"--objects {args.objects}: not a folder")
    return args


def override(params: PpfParams, spec: str) -> PpfParams:
    """`params` with the `name=value,…` of `spec` replaced (values parsed as the field's type)."""
    fields = {f.name: f for f in dataclasses.fields(PpfParams)}
    changes = {}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in fields:
            raise ValueError(f"{item!r}: expected NAME=VALUE with NAME one of {sorted(fields)}")
        kind = type(getattr(params, name))
        if kind is bool:
            if value.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"{name}={value!r}: expected true or false")
            changes[name] = value.lower() in ("true", "1")
        elif kind is str:
            changes[name] = value
        else:
            try:
                changes[name] = kind(eval_number(value)) if kind is float else int(value)
            except (ValueError, ZeroDivisionError):
                raise ValueError(f"{name}={value!r}: expected a number") from None
    out = dataclasses.replace(params, **changes)
    validate(out)
    return out


def eval_number(text: str) -> float:
    """A float, or a fraction `a/b` (as OpenCV's sample writes 1.0/40.0)."""
    if "/" in text:
        a, b = text.split("/", 1)
        return float(a) / float(b)
    return float(text)


def validate(p: PpfParams):
    if not (0 < p.rel_sampling < 1 and 0 < p.rel_distance < 1 and 0 < p.scene_distance < 1):
        raise ValueError("rel_sampling, rel_distance and scene_distance must be in (0, 1)")
    if not 0 < p.scene_step <= 1:
        raise ValueError("scene_step must be in (0, 1] (OpenCV asserts it)")
    if p.num_angles < 1 or p.hypotheses < 1 or p.icp_iterations < 1 or p.icp_levels < 0:
        raise ValueError("num_angles, hypotheses and icp_iterations must be >= 1 and icp_levels >= 0")
    if not (p.normal_radius > 0 and p.fit_distance > 0):
        raise ValueError("normal_radius and fit_distance must be positive")
    if p.select not in ("votes", "fit"):
        raise ValueError(f"select={p.select!r}: expected votes or fit")


# ---------------------------------------------------------------------------------------------
# Files: PLY point clouds and meshes (OBJ, PLY, OFF) with numpy only


PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
             "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
             "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply(path: Path):
    """{element: array} of a PLY file: vertices as a structured array, faces as a list of index
    arrays (other elements are skipped). ASCII and binary, either byte order."""
    import numpy as np

    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    body = data.index(b"\n", end) + 1
    fmt, elements = None, []
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        w = line.split()
        if not w or w[0] in ("comment", "obj_info"):
            continue
        if w[0] == "format":
            fmt = w[1]
        elif w[0] == "element":
            elements.append((w[1], int(w[2]), []))
        elif w[0] == "property" and elements:
            if w[1] == "list":
                elements[-1][2].append((w[4], "list", PLY_TYPES.get(w[2]), PLY_TYPES.get(w[3])))
            else:
                elements[-1][2].append((w[2], PLY_TYPES.get(w[1]), None, None))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unsupported PLY format {fmt!r}")
    for name, _, props in elements:
        for prop in props:
            if prop[1] is None or (prop[1] == "list" and (prop[2] is None or prop[3] is None)):
                raise ValueError(f"{path}: element {name}: unsupported property type in {prop[0]!r}")
    out = {}
    if fmt == "ascii":
        tokens = data[body:].split()
        pos = 0
        for name, count, props in elements:
            if all(p[1] != "list" for p in props):
                k = len(props)
                chunk = np.array(tokens[pos:pos + count * k], dtype=np.float64)
                if chunk.size != count * k:
                    raise ValueError(f"{path}: element {name}: file ends early")
                rows = chunk.reshape(count, k)
                pos += count * k
                arr = np.zeros(count, dtype=[(p[0], "f8") for p in props])
                for j, p in enumerate(props):
                    arr[p[0]] = rows[:, j]
                out[name] = arr
            else:
                lists = []
                for _ in range(count):
                    for p in props:
                        if p[1] == "list":
                            k = int(tokens[pos])
                            lists.append(np.array(tokens[pos + 1:pos + 1 + k], dtype=np.int64))
                            pos += 1 + k
                        else:
                            pos += 1
                out[name] = lists
        return out
    order = "<" if fmt == "binary_little_endian" else ">"
    pos = body
    for name, count, props in elements:
        if all(p[1] != "list" for p in props):
            dtype = np.dtype([(p[0], order + p[1]) for p in props])
            size = dtype.itemsize * count
            if pos + size > len(data):
                raise ValueError(f"{path}: element {name}: file ends early")
            out[name] = np.frombuffer(data, dtype=dtype, count=count, offset=pos)
            pos += size
            continue
        lists = []
        for _ in range(count):
            for p in props:
                if p[1] == "list":
                    ct, it = np.dtype(order + p[2]), np.dtype(order + p[3])
                    k = int(np.frombuffer(data, dtype=ct, count=1, offset=pos)[0])
                    pos += ct.itemsize
                    lists.append(np.frombuffer(data, dtype=it, count=k, offset=pos).astype(np.int64))
                    pos += it.itemsize * k
                else:
                    pos += np.dtype(p[1]).itemsize
        out[name] = lists
    return out


def xyz(vertex, path: Path):
    import numpy as np

    names = vertex.dtype.names or ()
    if not all(c in names for c in "xyz"):
        raise ValueError(f"{path}: the vertex element has no x, y, z")
    return np.stack([np.asarray(vertex[c], dtype=np.float64) for c in "xyz"], axis=1)


def read_points(path: Path):
    """The points of a PLY point cloud (n×3, float64); errors name the file."""
    import numpy as np

    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing")
    ply = read_ply(path)
    if "vertex" not in ply:
        raise ValueError(f"{path}: no vertex element")
    pts = xyz(ply["vertex"], path)
    if len(pts) == 0:
        raise ValueError(f"{path}: no points read")
    if not np.isfinite(pts).all():
        raise ValueError(f"{path}: non-finite coordinates")
    return pts


def triangulate(polygons, path: Path, nv: int):
    import numpy as np

    tris = [(f[0], f[k], f[k + 1]) for f in polygons for k in range(1, len(f) - 1)]
    if not tris:
        raise ValueError(f"{path}: no faces")
    F = np.asarray(tris, dtype=np.int64)
    if F.min() < 0 or F.max() >= nv:
        raise ValueError(f"{path}: a face index is out of range (0..{nv - 1})")
    return F


def load_mesh(path: Path):
    """(vertices n×3 float64, triangles m×3) of an OBJ, PLY or OFF mesh (polygons fanned)."""
    import numpy as np

    suffix = path.suffix.lower()
    if suffix == ".ply":
        ply = read_ply(path)
        if "vertex" not in ply or "face" not in ply:
            raise ValueError(f"{path}: a mesh needs vertex and face elements")
        V = xyz(ply["vertex"], path)
        return V, triangulate([list(f) for f in ply["face"]], path, len(V))
    text = path.read_text(errors="replace")
    if suffix == ".obj":
        verts, polys = [], []
        for line in text.splitlines():
            w = line.split()
            if not w:
                continue
            if w[0] == "v":
                verts.append([float(x) for x in w[1:4]])
            elif w[0] == "f":
                idx = [int(x.split("/")[0]) for x in w[1:]]
                polys.append([i - 1 if i > 0 else len(verts) + i for i in idx])
        V = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
        return V, triangulate(polys, path, len(V))
    if suffix == ".off":
        words = [w for line in text.splitlines() for w in line.split("#", 1)[0].split()]
        head = words[0]
        if head == "OFF":
            words = words[1:]
        elif head.startswith("OFF"):  # "OFF490 518 0" (ModelNet's glued header)
            words[0] = head[3:]
        else:
            raise ValueError(f"{path}: not an OFF file")
        nv, nf = int(words[0]), int(words[1])
        V = np.asarray(words[3:3 + 3 * nv], dtype=np.float64).reshape(nv, 3)
        pos, polys = 3 + 3 * nv, []
        for _ in range(nf):
            k = int(words[pos])
            polys.append([int(x) for x in words[pos + 1:pos + 1 + k]])
            pos += 1 + k
        return V, triangulate(polys, path, nv)
    raise ValueError(f"{path}: unsupported mesh format (use .obj, .ply or .off)")


def normalise(V):
    """As ic_geometry::Mesh::normalise: the bounding box centred at 0 and divided by half its
    longest side."""
    lo, hi = V.min(axis=0), V.max(axis=0)
    half = (hi - lo).max() / 2
    if not (half > 0 and math.isfinite(half)):
        raise ValueError("the mesh has no extent")
    return (V - (lo + hi) / 2) / half


# ---------------------------------------------------------------------------------------------
# Normals


def neighbour_pairs(points, queries, radius):
    """Yields (query index, point index, squared distance) arrays of every pair closer than
    `radius`, exactly (a uniform grid of cell `radius`, the 27 cells around each query)."""
    import numpy as np

    cells = np.floor(points / radius).astype(np.int64)
    qcells = np.floor(queries / radius).astype(np.int64)
    lo = np.minimum(cells.min(axis=0), qcells.min(axis=0)) - 1
    dims = np.maximum(cells.max(axis=0), qcells.max(axis=0)) - lo + 2

    def key(c):
        c = c - lo
        return (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]

    keys = key(cells)
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    r2 = radius * radius
    for off in np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T:
        k = key(qcells + off)
        start = np.searchsorted(sorted_keys, k, side="left")
        count = np.searchsorted(sorted_keys, k, side="right") - start
        total = int(count.sum())
        if total == 0:
            continue
        qi = np.repeat(np.arange(len(queries)), count)
        within = np.arange(total) - np.repeat(np.cumsum(count) - count, count)
        pi = order[np.repeat(start, count) + within]
        d2 = ((queries[qi] - points[pi]) ** 2).sum(axis=1)
        near = d2 <= r2
        yield qi[near], pi[near], d2[near]


def radius_normals(points, radius, toward=None, away_from=None):
    """Unit normals by a plane fit (the smallest principal axis of the covariance) over the
    points within `radius` of each point, itself included; oriented toward the point
    `toward` or away from the point `away_from`. Also a mask of the points with at least 3
    such points (the others get no normal)."""
    import numpy as np

    n = len(points)
    origin = points.mean(axis=0)
    p = points - origin  # better conditioned sums
    cnt = np.zeros(n)
    s = np.zeros((n, 3))
    ss = np.zeros((n, 3, 3))
    for qi, pi, _ in neighbour_pairs(p, p, radius):
        cnt += np.bincount(qi, minlength=n)
        q = p[pi]
        for a in range(3):
            s[:, a] += np.bincount(qi, weights=q[:, a], minlength=n)
            for b in range(a, 3):
                ss[:, a, b] += np.bincount(qi, weights=q[:, a] * q[:, b], minlength=n)
    for a in range(3):
        for b in range(a):
            ss[:, a, b] = ss[:, b, a]
    ok = cnt >= 3
    c = np.maximum(cnt, 1)[:, None]
    mean = s / c
    cov = ss / c[:, :, None] - mean[:, :, None] * mean[:, None, :]
    _, vecs = np.linalg.eigh(cov)
    normals = vecs[:, :, 0]
    ref = (toward - points) if toward is not None else (points - away_from)
    flip = (normals * ref).sum(axis=1) < 0
    normals[flip] *= -1
    ok &= np.isfinite(normals).all(axis=1)
    return normals, ok


def mesh_normals(points, V, F, chunk=256):
    """For each point, the unit normal of the nearest triangle of the mesh (V, F) and the
    distance to it. Normals are outward: each connected piece of the mesh is oriented so that
    its signed volume is positive (a closed piece's face normals then point out of it)."""
    import numpy as np

    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    cross = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cross, axis=1)
    good = area2 > 1e-12 * max(1.0, float(np.abs(V).max()) ** 2)
    if not good.any():
        raise ValueError("every face of the mesh is degenerate")
    # Connected pieces: vertex labels propagated along faces until stable.
    labels = np.arange(len(V))
    while True:
        m = labels[F].min(axis=1)
        new = labels.copy()
        np.minimum.at(new, F.ravel(), np.repeat(m, 3))
        new = new[new]
        if (new == labels).all():
            break
        labels = new
    piece = np.unique(labels[F[:, 0]], return_inverse=True)[1]
    volume = np.bincount(piece, weights=(a * np.cross(b, c)).sum(axis=1) / 6.0)
    sign = np.where(volume[piece] < 0, -1.0, 1.0)
    a, b, c = a[good], b[good], c[good]
    fn = cross[good] / area2[good, None] * sign[good, None]
    e0, e1 = b - a, c - a
    d00, d01, d11 = (e0 * e0).sum(1), (e0 * e1).sum(1), (e1 * e1).sum(1)
    den = d00 * d11 - d01 * d01

    def seg_d2(p, x, y):
        xy = y - x
        t = np.clip(((p - x) * xy).sum(-1) / np.maximum((xy * xy).sum(-1), 1e-300), 0, 1)
        return ((p - (x + t[..., None] * xy)) ** 2).sum(-1)

    normals = np.empty((len(points), 3))
    dist = np.empty(len(points))
    for s0 in range(0, len(points), chunk):
        p = points[s0:s0 + chunk, None, :]
        ap = p - a
        h = (ap * fn).sum(-1)
        d20, d21 = (ap * e0).sum(-1) - h * (fn * e0).sum(-1), (ap * e1).sum(-1) - h * (fn * e1).sum(-1)
        v = (d11 * d20 - d01 * d21) / den
        w = (d00 * d21 - d01 * d20) / den
        inside = (v >= 0) & (w >= 0) & (v + w <= 1)
        edges = np.minimum(np.minimum(seg_d2(p, a, b), seg_d2(p, b, c)), seg_d2(p, c, a))
        d2 = np.where(inside, h * h, edges)
        j = d2.argmin(axis=1)
        normals[s0:s0 + chunk] = fn[j]
        dist[s0:s0 + chunk] = np.sqrt(d2[np.arange(len(j)), j])
    return normals, dist


def manifest_folder(cases_root: Path):
    """The mesh folder named in the manifest.json that `cargo xtask export-cases` (or the bench)
    wrote next to the case folders; (folder or None, the reason when None)."""
    for name in ("manifest.json", "bench-manifest.json"):
        f = cases_root / name
        if not f.is_file():
            continue
        try:
            m = json.loads(f.read_text())
        except (OSError, json.JSONDecodeError) as e:
            return None, f"{f}: {e}"
        corpus = (m.get("config") or {}).get("corpus") or m.get("objects") or {}
        if corpus.get("kind") == "procedural":
            return None, (f"{f}: the cases were made from procedural objects, which have no mesh file "
                          "(use --model-normals estimate)")
        if corpus.get("folder"):
            return Path(corpus["folder"]), None
        return None, f"{f} names no mesh folder (pass --objects)"
    return None, f"no manifest.json in {cases_root} (pass --objects)"


class ModelNormals:
    """The model's normals for a case: from its mesh (found once per object) or estimated."""

    def __init__(self, args):
        self.mode = args.model_normals
        self.objects = args.objects
        self.meshes = {}

    def mesh_path(self, case: Path) -> Path:
        own = case / "model.ply"
        if own.is_file():
            return own
        meta_file = case / "meta.json"
        try:
            object_id = json.loads(meta_file.read_text())["object_id"]
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
            raise ValueError(f"{meta_file}: cannot read object_id ({error_text(e)})") from None
        folder = self.objects
        if folder is None:
            folder, why = manifest_folder(case.parent)
            if folder is None:
                raise FileNotFoundError(f"no mesh for {case}: {why}")
        for ext in MESH_EXTENSIONS:
            f = folder / f"{object_id}{ext}"
            if f.is_file():
                return f
        raise FileNotFoundError(f"no mesh for {case}: none of {folder}/{object_id}{{{','.join(MESH_EXTENSIONS)}}} "
                                "exists (pass --objects)")

    def __call__(self, case: Path, source):
        """(n×3 unit normals, details)."""
        import numpy as np

        if self.mode == "estimate":
            normals, ok = radius_normals(source, 0.1, away_from=source.mean(axis=0))
            radial = source - source.mean(axis=0)
            normals[~ok] = radial[~ok] / np.maximum(np.linalg.norm(radial[~ok], axis=1, keepdims=True), 1e-12)
            return normals, {"model_normals": "estimated (radius 0.1, away from the centroid)",
                             "model_normals_radial": int((~ok).sum())}
        path = self.mesh_path(case)
        if path not in self.meshes:
            try:
                V, F = load_mesh(path)
                self.meshes[path] = (normalise(V), F)
            except (OSError, ValueError) as e:
                msg = str(e)
                raise ValueError(msg if str(path) in msg else f"{path}: {msg}") from None
        V, F = self.meshes[path]
        normals, dist = mesh_normals(source, V, F)
        if dist.max() > MESH_TOLERANCE:
            raise ValueError(f"{case / 'source.ply'}: points lie up to {dist.max():.4f} units from the normalised "
                             f"mesh {path}; is it the mesh the case was exported from (and without scale "
                             "augmentation)?")
        return normals, {"model_normals": str(path), "mesh_distance_max": float(dist.max())}


# ---------------------------------------------------------------------------------------------
# OpenCV (imported lazily so that --check and --help work without it)


def import_cv2(threads: int):
    import cv2

    if not hasattr(cv2, "ppf_match_3d"):
        raise SystemExit(f"cv2 {cv2.__version__} has no ppf_match_3d module: install opencv-contrib-python-headless "
                         "(benches/peers/requirements-ppf.txt), not opencv-python")
    if threads > 0:
        cv2.setNumThreads(threads)
    return cv2


@dataclasses.dataclass
class Stage:
    """What the PPF stage left for the refinement: the scene with normals, the poses (most
    votes first) and its time."""

    scene: object
    poses: list
    votes: list
    seconds: float
    details: dict


def rigid(T):
    """(T with its 3×3 block replaced by the nearest rotation, the block's scale), or (None, scale)
    when the block is (nearly) singular.

    OpenCV averages the quaternions of each pose cluster without normalising them and builds the
    pose from the average, so a cluster of more than one pose comes out as s·R with s = |q̄|² < 1
    (a scaled rotation: its singular values are all s). The nearest rotation is R itself."""
    import numpy as np

    U, S, Vt = np.linalg.svd(T[:3, :3])
    scale = float(S.mean())
    if S.min() < 1e-3 or not np.isfinite(T).all():
        return None, scale
    out = T.copy()
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    out[3] = [0.0, 0.0, 0.0, 1.0]
    return out, scale


class Ppf:
    def __init__(self, cv2):
        self.cv2 = cv2

    def scene(self, params: PpfParams, target):
        """The observed points with normals (n×6 float32), camera at the origin; points
        without enough neighbours for a plane are left out."""
        import numpy as np

        normals, ok = radius_normals(target, params.normal_radius, toward=np.zeros(3))
        if not ok.any():
            raise ValueError(f"no target point has 3 neighbours within {params.normal_radius:.4f}: "
                             "cannot estimate normals")
        return np.hstack([target[ok], normals[ok]]).astype(np.float32), int((~ok).sum())

    def sampled_count(self, cloud, step):
        """How many points OpenCV's samplePCByQuantization keeps (for messages)."""
        lo, hi = cloud[:, :3].min(axis=0), cloud[:, :3].max(axis=0)
        s = self.cv2.ppf_match_3d.samplePCByQuantization(
            cloud, (float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1])), (float(lo[2]), float(hi[2])),
            float(step), 0)
        return len(s)

    def detect(self, params: PpfParams, model, target) -> Stage:
        import numpy as np

        t0 = time.perf_counter()
        scene, dropped = self.scene(params, target)
        t1 = time.perf_counter()
        detector = self.cv2.ppf_match_3d_PPF3DDetector(params.rel_sampling, params.rel_distance,
                                                       params.num_angles)
        detector.trainModel(model)
        t2 = time.perf_counter()
        results = detector.match(scene, params.scene_step, params.scene_distance)
        t3 = time.perf_counter()
        details = {"scene_points": len(scene), "no_normal": dropped, "normals_seconds": t1 - t0,
                   "train_seconds": t2 - t1, "match_seconds": t3 - t2, "poses": len(results)}
        if not results:
            k = self.sampled_count(scene, params.scene_distance)
            raise RuntimeError(
                f"OpenCV's PPF returned no pose: the scene sampled to {k} points and OpenCV keeps "
                f"floor({k} / {round(1 / params.scene_step)}) poses (relativeSceneSampleStep {params.scene_step:g})")
        poses, votes, scales = [], [], []
        for r in results:
            T, scale = rigid(np.array(r.pose, dtype=np.float64).reshape(4, 4))
            if T is not None:
                poses.append(T)
                votes.append(int(r.numVotes))
                scales.append(round(scale, 4))
        if not poses:
            raise RuntimeError(f"OpenCV's PPF returned {len(results)} poses and none has a usable rotation "
                               "(their cluster averages cancelled out)")
        details.update(votes=votes[:5], rotation_scales=scales[:5])
        return Stage(scene, poses, votes, t3 - t0, details)

    def fit(self, model, scene, T, distance):
        """The fraction of the model's points, moved by T, with a scene point within `distance`."""
        import numpy as np

        moved = model[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        hit = np.zeros(len(moved), dtype=bool)
        for qi, _, _ in neighbour_pairs(scene[:, :3].astype(np.float64), moved, distance):
            hit[qi] = True
        return float(hit.mean())

    def refine(self, params: PpfParams, model, stage: Stage):
        """ICP from the first `hypotheses` poses; (T, seconds, details)."""
        import numpy as np

        t0 = time.perf_counter()
        levels = icp_pyramid(params.icp_levels, len(model))
        icp = self.cv2.ppf_match_3d_ICP(params.icp_iterations, params.icp_tolerance, params.icp_rejection_scale,
                                        levels)
        best, fits = None, []
        for T0 in stage.poses[: params.hypotheses]:
            # OpenCV's multi-pose registerModelToScene does the same (move the model, register,
            # compose); the single-pose call avoids the Python binding's Pose3D handling.
            moved = np.hstack([model[:, :3] @ T0[:3, :3].T + T0[:3, 3], model[:, 3:] @ T0[:3, :3].T])
            _, residual, step = icp.registerModelToScene(moved.astype(np.float32), stage.scene)
            T = np.asarray(step, dtype=np.float64).reshape(4, 4) @ T0
            if params.select == "votes":
                best = T
                break
            f = self.fit(model, stage.scene, T, params.fit_distance)
            fits.append(round(f, 4))
            if best is None or f > best[1]:
                best = (T, f)
        T = best if params.select == "votes" else best[0]
        seconds = time.perf_counter() - t0
        details = {"icp_seconds": seconds, "icp_levels": levels, "refined": min(params.hypotheses, len(stage.poses))}
        if fits:
            details["fits"] = fits
        return T, seconds, details

    def run(self, params: PpfParams, model, target, stage: Stage | None = None):
        """(4×4 pose, seconds, details, stage). A given `stage` (same ppf_key) is reused and its
        time counted."""
        if stage is None:
            stage = self.detect(params, model, target)
        details = dict(stage.details)
        if not params.icp:
            return stage.poses[0], stage.seconds, details, stage
        T, seconds, more = self.refine(params, model, stage)
        details.update(more)
        return T, stage.seconds + seconds, details, stage


def params_config(args):
    return {PREFIX + m: dataclasses.asdict(args.params[m]) for m in args.methods}


# ---------------------------------------------------------------------------------------------
# Modes


def run_cases(args):
    import numpy as np

    cv2 = import_cv2(args.threads)
    ppf = Ppf(cv2)
    model_normals = ModelNormals(args)
    dirs = case_dirs(args.cases)
    if args.limit:
        dirs = dirs[: args.limit]
    config = {"cases": str(args.cases), "out": str(args.out), "methods": [PREFIX + m for m in args.methods],
              "seed": args.seed, "max_target_points": args.max_target_points,
              "threads": args.threads or "opencv default", "opencv_threads": cv2.getNumThreads(),
              "opencv": cv2.__version__, "case_count": len(dirs), "model_normals": args.model_normals,
              "objects": str(args.objects) if args.objects else "from manifest.json",
              "params": params_config(args)}
    print(f"ppf_peers seed {args.seed} config {json.dumps(config)}", flush=True)

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
            load_error, info = None, {}
            try:
                source = read_points(d / "source.ply")
                target = cap_points(read_points(d / "target.ply"), args.max_target_points,
                                    derived_seed(args.seed, name, "cap"))
                normals, info = model_normals(d, source)
                model = np.hstack([source, normals]).astype(np.float32)
            except Exception as e:  # noqa: BLE001 - a broken case must not stop the run
                load_error = error_text(e)
            stages = {}  # ppf_key -> Stage, or the PPF stage's error: shared within the case
            for m in pending:
                n += 1
                rec = case_record(name, PREFIX + m, load_error)
                if load_error is None:
                    params = args.params[m]
                    key = params.ppf_key()
                    try:
                        cv2.setRNGSeed(derived_seed(args.seed, name, m))
                        if key not in stages:
                            try:
                                stages[key] = ppf.detect(params, model, target)
                            except Exception as e:  # noqa: BLE001
                                stages[key] = e
                        if isinstance(stages[key], Exception):
                            raise stages[key]
                        T, seconds, details, _ = ppf.run(params, model, target, stages[key])
                        record_pose(rec, T, seconds)
                        if args.details:
                            rec["details"] = {"source_points": len(source), "target_points": len(target),
                                              **info, **details}
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

    cv2 = import_cv2(args.threads)
    ppf = Ppf(cv2)
    case = None
    if args.cases is not None:
        case = args.cases if (args.cases / "source.ply").is_file() else case_dirs(args.cases)[0]
        source_all = read_points(case / "source.ply")
        target_all = read_points(case / "target.ply")
        normals_all, _ = ModelNormals(args)(case, source_all)
    config = {"mode": "timing", "points": [size_label(*size) for size in args.sizes], "repeats": args.repeats,
              "seed": args.seed, "methods": [PREFIX + m for m in args.methods],
              "threads": args.threads or "opencv default",
              "pair": str(case) if case else "synthetic bumpy ellipsoid", "params": params_config(args)}
    print(f"ppf_peers seed {args.seed} config {json.dumps(config)}", flush=True)
    results = []
    total, k = len(args.sizes) * len(args.methods), 0
    for n_model, n_obs in args.sizes:
        # The seeds' key: str(n) for a square size (the draws of plain `--points N`), else "MxN".
        size = size_label(n_model, n_obs)
        if case is None:
            source, normals, target = synthetic_pair(n_model, derived_seed(args.seed, "timing"), with_normals=True,
                                                     observed=n_obs)
        else:
            # The same draws as open3d_peers.py --timing: the same (n_model, n_obs)-point pair.
            rng = np.random.default_rng(derived_seed(args.seed, "timing", size))
            idx, jitter = resample_indices(len(source_all), n_model, rng)
            source, normals = source_all[idx] + jitter, normals_all[idx]
            idx, jitter = resample_indices(len(target_all), n_obs, rng)
            target = target_all[idx] + jitter
        model = np.hstack([source, normals]).astype(np.float32)
        stages = {}
        for m in args.methods:
            k += 1
            params = args.params[m]
            runs, details, error = [], {}, None
            try:
                # A method that shares the PPF stage of one timed before it (ppf-icp after ppf)
                # reuses that method's stage of the same repeat and adds its time: the same
                # total as running it again, for half the work.
                key = params.ppf_key()
                cv2.setRNGSeed(derived_seed(args.seed, "timing", size, m))
                ppf.run(params, model, target, stages.get((key, 0)))  # warm-up, not counted
                for i in range(args.repeats):
                    _, seconds, details, stage = ppf.run(params, model, target, stages.get((key, i)))
                    stages.setdefault((key, i), stage)
                    runs.append(seconds)
            except Exception as e:  # noqa: BLE001
                error = error_text(e)
            results.append(timing_record(PREFIX + m, n_model, n_obs, runs, error, k, total,
                                         scene_points=details.get("scene_points"),
                                         train_seconds=details.get("train_seconds"),
                                         match_seconds=details.get("match_seconds")))
    report = {"machine": machine_info(cv2.getNumThreads()), "opencv_version": cv2.__version__,
              "threads": args.threads or cv2.getNumThreads(), "seed": args.seed, "repeats": args.repeats,
              "pair": config["pair"], "config": config["params"], "results": results}
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

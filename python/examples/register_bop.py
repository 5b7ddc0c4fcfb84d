#!/usr/bin/env python3
"""Registers one object in every image of one BOP scene folder and prints the poses.

    python register_bop.py SCENE_DIR OBJ_ID [--models MODELS_DIR] [--masks] [--seed 0]

SCENE_DIR is a BOP scene (e.g. lm/test/000002): scene_camera.json (cam_K and depth_scale
per image), depth/*.png (16-bit, value × depth_scale = mm) and, with --masks,
mask_visib/*.png with scene_gt.json to pick the object's instance. The mesh is
MODELS_DIR/obj_XXXXXX.ply (default: SCENE_DIR/../../models), in mm as in every BOP dataset.
Prints one line per image: image id, verdict, confidence, cam_R_m2c (row-major) and
cam_t_m2c (mm), as BOP's scene_gt.json holds them.
"""

import argparse
import json
import sys
from pathlib import Path

import incontext


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, help="a BOP scene folder (scene_camera.json, depth/)")
    ap.add_argument("obj_id", type=int, help="the object's BOP id (models/obj_XXXXXX.ply)")
    ap.add_argument("--models", type=Path, help="the models folder (default: SCENE/../../models)")
    ap.add_argument("--masks", action="store_true", help="use mask_visib/ instead of the segmentation network")
    ap.add_argument("--seed", type=int, default=0, help="seed of every random choice")
    ap.add_argument("--threads", type=int, default=None, help="compute threads (default: all CPUs)")
    args = ap.parse_args()

    models = args.models or args.scene.parent.parent / "models"
    model = incontext.Model.from_file(models / f"obj_{args.obj_id:06d}.ply", unit_mm=1.0)
    registrar = incontext.Registrar(seed=args.seed, threads=args.threads)
    cameras = json.loads((args.scene / "scene_camera.json").read_text())
    gt = json.loads((args.scene / "scene_gt.json").read_text()) if args.masks else {}

    for im_id in sorted(cameras, key=int):
        entry = cameras[im_id]
        depth = incontext.read_depth_png(args.scene / "depth" / f"{int(im_id):06d}.png")
        h, w = depth.shape
        camera = incontext.Camera(entry["cam_K"], w, h, depth_scale=entry.get("depth_scale", 1.0))
        mask = None
        if args.masks:
            instances = [i for i, o in enumerate(gt.get(im_id, [])) if o["obj_id"] == args.obj_id]
            if not instances:
                print(f"{im_id}: object {args.obj_id} not in scene_gt.json", file=sys.stderr)
                continue
            name = f"{int(im_id):06d}_{instances[0]:06d}.png"
            mask = incontext.read_mask_png(args.scene / "mask_visib" / name)
        try:
            r = registrar.register(model, depth, camera, mask=mask)
        except incontext.NotFoundError as e:
            print(f"{im_id}: not_found ({e})")
            continue
        bop = r.to_bop()
        R = " ".join(f"{x:.6f}" for x in bop["cam_R_m2c"])
        t = " ".join(f"{x:.3f}" for x in bop["cam_t_m2c"])
        print(f"{im_id}: {r.verdict} confidence {r.confidence:.3f} cam_R_m2c [{R}] cam_t_m2c [{t}] mm "
              f"({r.timings['total']:.0f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

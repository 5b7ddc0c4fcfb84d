"""examples/register_bop.py on a BOP scene folder made of the demo's files."""

import json
import shutil
import subprocess
import sys

from conftest import ROOT


def test_register_bop_prints_the_pose_of_every_image(demo, tmp_path):
    dataset = tmp_path / "bop"
    scene = dataset / "test" / "000001"
    (scene / "depth").mkdir(parents=True)
    (scene / "mask_visib").mkdir()
    (dataset / "models").mkdir()
    shutil.copy(demo / "model.ply", dataset / "models" / "obj_000001.ply")
    cam = json.loads((demo / "camera.json").read_text())
    truth = json.loads((demo / "gt_pose.json").read_text())
    cameras, gts = {}, {}
    for im in (0, 1):
        shutil.copy(demo / "depth.png", scene / "depth" / f"{im:06d}.png")
        shutil.copy(demo / "mask_gt.png", scene / "mask_visib" / f"{im:06d}_000000.png")
        cameras[str(im)] = {"cam_K": cam["cam_K"], "depth_scale": cam["depth_scale"]}
        gts[str(im)] = [{"obj_id": 1, **truth["bop"]}]
    (scene / "scene_camera.json").write_text(json.dumps(cameras))
    (scene / "scene_gt.json").write_text(json.dumps(gts))
    example = ROOT / "python" / "examples" / "register_bop.py"
    p = subprocess.run(
        [sys.executable, str(example), str(scene), "1", "--masks", "--seed", "3"],
        capture_output=True, text=True, timeout=600,
    )
    assert p.returncode == 0, p.stderr
    lines = p.stdout.splitlines()
    assert len(lines) == 2 and lines[0].startswith("0: ") and lines[1].startswith("1: "), p.stdout
    for line in lines:
        assert "cam_R_m2c [" in line and "cam_t_m2c [" in line, line
    # The same image twice, the same seed: the same pose.
    assert lines[0].split(" (")[0][3:] == lines[1].split(" (")[0][3:]

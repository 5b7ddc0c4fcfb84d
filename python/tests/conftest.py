"""Shared fixtures: the `incontext` command line (built by cargo) and the demo scene it
writes (model.ply in mm, depth.png with depth_scale 1, camera.json, mask_gt.png)."""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

import incontext

ROOT = Path(__file__).resolve().parents[2]
SEED = 3
# xtask's `TEST_FEATURES`: the features `cargo xtask test` builds the workspace with.
TEST_FEATURES = "ic_render/gpu"


@pytest.fixture(scope="session")
def cli() -> Path:
    """The `incontext` binary of this workspace (dev profile, as `cargo xtask test` builds it).

    `--workspace` with `TEST_FEATURES` (xtask/src/main.rs) resolves the features `cargo xtask
    test` builds the tests with, so the binary that build made is reused; `-p incontext` alone
    resolves fewer and rebuilds candle and the engine.
    """
    cargo = os.environ.get("CARGO", "cargo")
    subprocess.run(
        [cargo, "build", "-q", "--workspace", "--features", TEST_FEATURES, "--bin", "incontext"],
        cwd=ROOT,
        check=True,
    )
    exe = ROOT / "target" / "debug" / "incontext"
    assert exe.is_file(), f"{exe} was not built"
    return exe


def run_cli(cli: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(cli), *args], cwd=ROOT, capture_output=True, text=True, timeout=600
    )


@pytest.fixture(scope="session")
def demo(cli: Path, tmp_path_factory) -> Path:
    """`incontext demo --seed 3`'s folder."""
    out = tmp_path_factory.mktemp("demo") / "scene"
    p = run_cli(cli, "demo", "--seed", str(SEED), "--out", str(out), "-q")
    assert p.returncode == 0, p.stderr
    return out


@pytest.fixture(scope="session")
def scene(demo: Path):
    """The demo's inputs as arrays: (model, depth uint16, camera, gt mask)."""
    cam = json.loads((demo / "camera.json").read_text())
    camera = incontext.Camera(
        np.array(cam["cam_K"]).reshape(3, 3), cam["width"], cam["height"], cam["depth_scale"]
    )
    model = incontext.Model.from_file(demo / "model.ply")
    depth = incontext.read_depth_png(demo / "depth.png")
    mask = incontext.read_mask_png(demo / "mask_gt.png")
    return model, depth, camera, mask


@pytest.fixture(scope="session")
def registrar() -> incontext.Registrar:
    """The settings and seed of `incontext register --seed 3`."""
    return incontext.Registrar(seed=SEED)


@pytest.fixture(scope="session")
def fast() -> incontext.Registrar:
    """One rotation, unverified: for tests about inputs rather than accuracy."""
    return incontext.Registrar(seed=SEED, rotations=1)

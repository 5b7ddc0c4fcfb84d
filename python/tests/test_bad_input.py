"""Every bad input of the command line's bad-input tests (crates/incontext/tests/cli.rs), from
Python: the right exception (ValueError for bad input, NotFoundError — a LookupError — for an
object not found), with the file or argument named; never a PanicException."""

import json
import struct

import numpy as np
import pytest

import incontext

from conftest import ROOT


def raises(exc, *needles):
    """pytest.raises that also checks the message holds every needle."""

    class Check:
        def __enter__(self):
            self.ctx = pytest.raises(exc)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *a):
            done = self.ctx.__exit__(*a)
            message = str(self.info.value)
            for n in needles:
                assert n in message, f"{n!r} not in {message!r}"
            # A panic would be a pyo3_runtime.PanicException (a BaseException): never expected.
            assert type(self.info.value).__name__ != "PanicException"
            return done

    return Check()


def write_json(path, value):
    path.write_text(json.dumps(value))
    return path


def test_missing_or_unreadable_files_are_value_errors(tmp_path, demo):
    with raises(ValueError, "nope.ply", "cannot read"):
        incontext.Model.from_file(tmp_path / "nope.ply")
    with raises(ValueError, "nope.png"):
        incontext.read_depth_png(tmp_path / "nope.png")
    with raises(ValueError, "nope.json", "cannot read"):
        incontext.Camera.from_file(tmp_path / "nope.json")
    with raises(ValueError, "nope_mask.png"):
        incontext.read_mask_png(tmp_path / "nope_mask.png")
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"not a png at all")
    with raises(ValueError, "garbage.png"):
        incontext.read_depth_png(garbage)
    bad_json = tmp_path / "garbage.json"
    bad_json.write_text("{ cam_K: ")
    with raises(ValueError, "garbage.json", "not valid JSON"):
        incontext.Camera.from_file(bad_json)
    with raises(ValueError, "nope.ply", "pose model"):
        incontext.Registrar(pose_model=tmp_path / "nope.ply")


def test_a_depth_map_of_another_size_than_the_camera_is_a_value_error(scene):
    model, depth, camera, mask = scene
    K = camera.K.copy()
    K[:2] /= 2
    half = incontext.Camera(K, camera.width // 2, camera.height // 2, camera.depth_scale)
    h, w = depth.shape
    with raises(ValueError, "depth", f"{w}×{h}", f"expected {w // 2}×{h // 2}"):
        incontext.Registrar(rotations=1).register(model, depth, half)
    with raises(ValueError, "mask", f"expected {w}×{h}"):
        incontext.Registrar(rotations=1).register(model, depth, camera, mask=mask[: h // 2])


def test_wrong_bit_depth_channels_or_dtype_is_a_value_error(demo, scene, fast):
    model, depth, camera, mask = scene
    # An 8-bit PNG read as depth, a 16-bit PNG read as a mask.
    with raises(ValueError, "mask_gt.png", "16-bit", "8-bit"):
        incontext.read_depth_png(demo / "mask_gt.png")
    with raises(ValueError, "depth.png", "8-bit", "16-bit"):
        incontext.read_mask_png(demo / "depth.png")
    # The same as arrays: an 8-bit depth map, three channels, complex numbers, one dimension.
    with raises(ValueError, "depth", "uint8"):
        fast.register(model, mask.astype(np.uint8), camera)
    with raises(ValueError, "depth", "3 channels"):
        fast.register(model, np.stack([depth] * 3, axis=-1), camera)
    with raises(ValueError, "depth", "complex"):
        fast.register(model, depth.astype(np.complex64), camera)
    with raises(ValueError, "depth", "shape (H, W)", f"({depth.size},)"):
        fast.register(model, depth.ravel(), camera)
    with raises(ValueError, "depth", "cannot be read as an array"):
        fast.register(model, [[1, 2], [3]], camera)
    with raises(ValueError, "mask", "float32"):
        fast.register(model, depth, camera, mask=mask.astype(np.float32))
    with raises(ValueError, "mask", "(H, W)"):
        fast.register(model, depth, camera, mask=mask[None])
    with raises(ValueError, "points", "(N, 3)"):
        fast.register_points(model, np.zeros((10, 2)))
    with raises(ValueError, "points", "not finite"):
        fast.register_points(model, np.full((100, 3), np.nan))
    with raises(TypeError):
        fast.register(model, depth, "camera.json")


def test_all_zero_or_nan_depth_is_a_value_error(scene, fast):
    model, depth, camera, _ = scene
    with raises(ValueError, "depth", "no valid pixel"):
        fast.register(model, np.zeros_like(depth), camera)
    with raises(ValueError, "depth", "no valid pixel"):
        fast.register(model, np.full(depth.shape, np.nan, np.float32), camera)
    with raises(ValueError, "depth", "beyond", "depth_scale"):
        fast.register(model, np.full(depth.shape, 1e12, np.float32), camera)


def test_non_positive_focal_length_is_a_value_error(tmp_path):
    for fx in (0.0, -131.25):
        with raises(ValueError, "camera", "focal lengths must be positive"):
            incontext.Camera([[fx, 0, 79.5], [0, 131.25, 59.5], [0, 0, 1]], 160, 120, 0.1)
        path = write_json(
            tmp_path / "fx.json",
            {"cam_K": [fx, 0, 79.5, 0, 131.25, 59.5, 0, 0, 1], "depth_scale": 0.1, "width": 160, "height": 120},
        )
        with raises(ValueError, "fx.json", "focal lengths must be positive"):
            incontext.Camera.from_file(path)
    no_k = write_json(tmp_path / "no_k.json", {"depth_scale": 0.1, "width": 160, "height": 120})
    with raises(ValueError, "no_k.json", "cam_K"):
        incontext.Camera.from_file(no_k)
    with raises(ValueError, "K", "shape (3, 3)"):
        incontext.Camera(np.eye(2), 160, 120)
    with raises(ValueError, "camera", "skew"):
        incontext.Camera([131.25, 2, 79.5, 0, 131.25, 59.5, 0, 0, 1], 160, 120)
    with raises(ValueError, "camera", "width", "-1"):
        incontext.Camera([131.25, 0, 79.5, 0, 131.25, 59.5, 0, 0, 1], -1, 120)
    with raises(ValueError, "camera", "depth_scale"):
        incontext.Camera([131.25, 0, 79.5, 0, 131.25, 59.5, 0, 0, 1], 160, 120, depth_scale=0)
    with raises(ValueError, "camera", "cam_K", "not a finite number"):
        incontext.Camera([np.inf, 0, 79.5, 0, 131.25, 59.5, 0, 0, 1], 160, 120)


def test_a_mesh_without_faces_is_a_value_error(demo, tmp_path):
    with raises(ValueError, "no_faces.obj", "no faces"):
        incontext.Model.from_file(ROOT / "fixtures" / "cli" / "no_faces.obj")
    with raises(ValueError, "cloud_binary_le.ply", "no faces"):
        incontext.Model.from_file(ROOT / "fixtures" / "meshes" / "cloud_binary_le.ply")
    with raises(ValueError, "camera.json", "unsupported mesh format"):
        incontext.Model.from_file(demo / "camera.json")
    v = np.zeros((3, 3))
    with raises(ValueError, "no faces"):
        incontext.Model(v, np.zeros((0, 3), np.int64))
    with raises(ValueError, "faces", "integer"):
        incontext.Model(v, np.zeros((1, 3)))
    with raises(ValueError, "faces", "refers to vertex 3"):
        incontext.Model(v, [[0, 1, 3]])
    with raises(ValueError, "faces", "refers to vertex -1"):
        incontext.Model(v, [[0, 1, -1]])
    with raises(ValueError, "vertices", "shape (N, 3)"):
        incontext.Model(np.zeros((3, 2)), [[0, 1, 2]])
    with raises(ValueError, "non-finite"):
        incontext.Model([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], [[0, 1, 2]])


def checkpoint_of_another_shape(tmp_path):
    """The shipped pose checkpoint with its recorded configuration changed to another shape."""
    data = (ROOT / "models" / "pose-cpu-softmax.safetensors").read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + n])
    config = json.loads(header["__metadata__"]["ic_pose.config"])
    config["net"]["emb_dims"] = 64
    header["__metadata__"]["ic_pose.config"] = json.dumps(config)
    new = json.dumps(header).encode()
    path = tmp_path / "other-shape.safetensors"
    path.write_bytes(struct.pack("<Q", len(new)) + new + data[8 + n :])
    return path


def test_a_checkpoint_of_another_network_shape_is_a_value_error(demo, tmp_path):
    with raises(ValueError, "other-shape.safetensors", "does not match its configuration"):
        incontext.Registrar(pose_model=checkpoint_of_another_shape(tmp_path))
    with raises(ValueError, "camera.json"):
        incontext.Registrar(pose_model=demo / "camera.json")
    with raises(ValueError, "model.ply", "segmentation model"):
        incontext.Registrar(seg_model=demo / "model.ply")
    with raises(ValueError, "camera.json", "second pose model"):
        incontext.Registrar(second_pose_model=demo / "camera.json")
    with raises(ValueError, "second_pose_model", "second_pose is False"):
        incontext.Registrar(second_pose_model=demo / "camera.json", second_pose=False)


def test_an_empty_mask_is_a_value_error(scene, fast):
    model, depth, camera, mask = scene
    with raises(ValueError, "mask", "mask is empty"):
        fast.register(model, depth, camera, mask=np.zeros_like(mask))
    corner = np.zeros_like(mask)
    corner[0, 0] = True
    depth = depth.copy()
    depth[0, 0] = 0
    with raises(ValueError, "mask", "no pixel with a valid depth"):
        fast.register(model, depth, camera, mask=corner)


def test_a_sliver_of_object_is_not_found(scene, fast):
    model, depth, camera, mask = scene
    sliver = np.zeros_like(mask)
    v, u = np.nonzero(mask & (depth > 0))
    sliver[v[:5], u[:5]] = True
    with raises(incontext.NotFoundError, "object not found") as info:
        fast.register(model, depth, camera, mask=sliver)
    assert isinstance(info.value, LookupError)


def test_a_depth_map_without_the_object_is_not_found(scene, registrar):
    model, depth, camera, _ = scene
    flat = np.full(depth.shape, 1000, np.uint16)  # a wall 1 m away
    with raises(LookupError, "object not found"):
        registrar.register(model, flat, camera)


def test_bad_settings_are_value_errors(demo):
    with raises(ValueError, "head", "softmax or ot"):
        incontext.Registrar(head="sinkhorn2")
    with raises(ValueError, "refine", "icp or none"):
        incontext.Registrar(refine="gn")
    with raises(ValueError, "unit_mm must be positive"):
        incontext.Model.from_file(demo / "model.ply", unit_mm=0)
    with raises(ValueError, "unit_mm must be positive"):
        incontext.Model([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], unit_mm=-1)
    with raises(ValueError, "threads"):
        incontext.Registrar(threads=0)
    with raises(ValueError, "rotations"):
        incontext.Registrar(rotations=7)
    with raises(ValueError, "hypotheses"):
        incontext.Registrar(hypotheses=0)
    for keys in (0, -3, "most", 2.5):
        with raises(ValueError, "attention_keys"):
            incontext.Registrar(attention_keys=keys)
    with raises(ValueError, "pose", "bottom row"):
        model = incontext.Model.from_file(demo / "model.ply")
        camera = incontext.Camera.from_file(demo / "camera.json")
        incontext.render(model, np.ones((4, 4)), camera)
    with raises(ValueError, "pose", "shape (4, 4)"):
        incontext.render(model, np.eye(3), camera)


def test_a_point_cloud_larger_than_any_depth_map_is_a_value_error(demo):
    model = incontext.Model.from_file(demo / "model.ply")
    # A broadcast view: 2²⁵ + 1 rows that take no memory; refused on its shape, before a copy.
    huge = np.broadcast_to(np.zeros(3, np.float32), (2**25 + 1, 3))
    with raises(ValueError, "points", "subsample"):
        incontext.Registrar(threads=1).register_points(model, huge)

"""incontext: the 6D pose of a known mesh in one depth map (CPU, no network, no GPU).

A thin layer over the Rust engine of ``incontext register``: the same networks, checks,
messages and, with the same seed, the same poses bit for bit.

Units and frames (as on the command line):

- a mesh is in its own units, ``unit_mm`` millimetres each (1 for BOP meshes in mm);
- depth values are the sensor's: ``value × depth_scale = mm`` (the BOP convention), 0 = no
  return;
- poses map model to camera coordinates (x right, y down, z forward), ``x_cam = R·x + t``,
  with ``t`` in millimetres.

Example::

    import incontext
    model = incontext.Model.from_file("obj_000001.ply")               # mesh in mm
    camera = incontext.Camera(K, 640, 480, depth_scale=0.1)           # K: (3, 3), pixels
    result = incontext.Registrar(seed=0).register(model, depth, camera)  # depth: (H, W) uint16
    print(result.R, result.t, result.confidence, result.verdict)

Errors: ``ValueError`` for bad input (the message names the file or argument),
``incontext.NotFoundError`` (a ``LookupError``) when the object is not found.
"""

import os as _os

# candle's CPU pool spins for a long time after every op, which slows the engine's own
# threads on small machines; the command line sets the same (ic_pose::CANDLE_CPU_ENV). Set
# before the extension starts any thread.
_os.environ.setdefault("CANDLE_BARRIER_POOL_SPIN_LIMIT", "200")

from ._incontext import (  # noqa: E402
    Camera,
    Model,
    NotFoundError,
    Registrar,
    Result,
    __version__,
    read_depth_png,
    read_mask_png,
    render,
)

__all__ = [
    "Camera",
    "Model",
    "NotFoundError",
    "Registrar",
    "Result",
    "__version__",
    "read_depth_png",
    "read_mask_png",
    "render",
]

"""Type hints of the extension module ``incontext._incontext`` (re-exported by ``incontext``).

Units: meshes in their own units (``unit_mm`` mm each); depth values ``× depth_scale = mm``
(BOP), 0 = no return; poses model → camera (x right, y down, z forward), ``t`` in mm.
"""

import os
from typing import Dict, List, Optional, Tuple, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, os.PathLike]
_Array = npt.ArrayLike

__version__: str

class NotFoundError(LookupError):
    """The object was not found in the depth map (the command line's exit code 3)."""

class Model:
    """A known object's mesh in its own units, ``unit_mm`` millimetres each."""

    def __init__(self, vertices: _Array, faces: _Array, unit_mm: float = 1.0) -> None:
        """``vertices``: (V, 3) real numbers (mesh units); ``faces``: (F, 3) integer indices."""
    @staticmethod
    def from_file(path: _Path, unit_mm: float = 1.0) -> "Model":
        """Reads an OBJ, PLY, OFF or glTF/GLB mesh in its own units (``unit_mm`` mm each)."""
    @property
    def vertices(self) -> npt.NDArray[np.float32]:
        """(V, 3) float32, mesh units."""
    @property
    def faces(self) -> npt.NDArray[np.int64]:
        """(F, 3) int64 vertex indices."""
    @property
    def unit_mm(self) -> float:
        """Millimetres per mesh unit."""

class Camera:
    """A pinhole camera: ``K`` in pixels, the image size, ``value × depth_scale = mm``."""

    def __init__(self, K: _Array, width: int, height: int, depth_scale: float = 1.0) -> None:
        """``K``: (3, 3) or 9 numbers row-major (BOP's cam_K), pixels."""
    @staticmethod
    def from_file(
        path: _Path, width: Optional[int] = None, height: Optional[int] = None
    ) -> "Camera":
        """Reads a camera JSON as ``incontext register --camera`` does."""
    @property
    def K(self) -> npt.NDArray[np.float64]:
        """(3, 3) float64, pixels."""
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def depth_scale(self) -> float:
        """``value × depth_scale = mm``."""

class Result:
    """One registration: pose model → camera (t in mm), confidence, verdict, timings."""

    @property
    def R(self) -> npt.NDArray[np.float64]:
        """(3, 3) rotation, model → camera."""
    @property
    def t(self) -> npt.NDArray[np.float64]:
        """(3,) translation in millimetres, camera frame."""
    @property
    def T(self) -> npt.NDArray[np.float64]:
        """(4, 4) ``[[R, t], [0, 0, 0, 1]]``, t in millimetres."""
    @property
    def confidence(self) -> float:
        """In [0, 1]: the calibrated probability that the pose is right."""
    @property
    def calibration(self) -> str:
        """"object" (a mask was given, or one instance only), "segmentation" (the network chose among several instances; calibrated on clutter) or "none"."""
    @property
    def verdict(self) -> str:
        """"ok" or "uncertain" ("not_found" raises NotFoundError)."""
    @property
    def timings(self) -> Dict[str, float]:
        """Milliseconds per stage."""
    @property
    def mask(self) -> Optional[npt.NDArray[np.bool_]]:
        """(H, W) bool: the object's pixels used (None for register_points)."""
    @property
    def object_voxels(self) -> int: ...
    @property
    def verification(self) -> Optional[Dict[str, float]]:
        """Render-and-compare scores in [0, 1] (score, coverage, agreement, visible_agreement, violation; misfit, the agreeing pixels' mean depth residual in units of their tolerance) as ``details.verification`` of ``incontext register --json``; None when not verified (rotations=1)."""
    @property
    def whole_view(self) -> Optional[Dict[str, float]]:
        """The model rendered at the pose over the whole image against the depth map, as ``details.whole_view`` of ``incontext register --json``: rendered_pixels, visible_pixels (not hidden behind a nearer observed surface), and the shares of the visible ones in agreement, in_front of the observed surface, or missing (no return); None for point inputs."""
    def to_bop(self) -> Dict[str, List[float]]:
        """{"cam_R_m2c": 9 floats row-major, "cam_t_m2c": 3 floats in mm}."""

class Registrar:
    """The engine with the settings of ``incontext register``; ``seed`` seeds every choice."""

    def __init__(
        self,
        head: Optional[str] = "softmax",
        refine: str = "icp",
        threads: Optional[int] = None,
        seed: int = 0,
        *,
        rotations: int = 24,
        hypotheses: int = 1,
        verify_top: int = 8,
        pose_model: Optional[_Path] = None,
        seg_model: Optional[_Path] = None,
        second_pose_model: Optional[_Path] = None,
        second_pose: bool = True,
        attention_keys: Optional[Union[int, str]] = None,
    ) -> None:
        """``attention_keys``: the pose networks' attention keys per cloud (an int ≥ 1, fewer is faster) or ``"all"`` (every point); None: each network's own, as ``register --attention-keys``."""
    def register(
        self,
        model: Model,
        depth: _Array,
        camera: Camera,
        mask: Optional[_Array] = None,
    ) -> Result:
        """``depth``: (H, W) uint16 or float32, ``value × camera.depth_scale = mm``."""
    def register_points(self, model: Model, points: _Array) -> Result:
        """``points``: (N, 3) observed object points in mm, camera frame."""
    @property
    def seed(self) -> int: ...
    @property
    def threads(self) -> Optional[int]: ...

def render(
    model: Model, pose: Union[_Array, Result], camera: Camera
) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """(depth (H, W) float32 with ``value × depth_scale = mm``, mask (H, W) bool)."""

def read_depth_png(path: _Path) -> npt.NDArray[np.uint16]:
    """A 16-bit grayscale PNG's stored values (BOP depth: ``value × depth_scale = mm``)."""

def read_mask_png(path: _Path) -> npt.NDArray[np.bool_]:
    """An 8-bit mask PNG, non-zero = object."""

//! `incontext._incontext`: the Python module, a thin layer over the `incontext` crate.
//!
//! Arrays are converted here (dtype, shape, memory order: NumPy arrays in any order and byte
//! order, lists, other integer and float types where that is sensible) and handed to
//! [`incontext::arrays`], which makes the command line's checks with its messages; the engine
//! runs with the GIL released. Errors: `ValueError` for bad input, `incontext.NotFoundError`
//! (a `LookupError`) when the object is not found, `RuntimeError` for internal errors.
//!
//! Units (as on the command line): a mesh is in its own units, `unit_mm` millimetres each;
//! depth values are the sensor's, `value × depth_scale = mm` (BOP); poses map model to camera
//! coordinates (x right, y down, z forward), `x_cam = R·x + t`, with `t` in millimetres here.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use ic_geometry::glam::{DVec3, Vec3};
use ic_geometry::{Mesh, Pose};
use incontext::arrays::{self, DepthValues};
use incontext::inputs::{self, CameraFile};
use incontext::pipeline::{Object, Pipeline, PipelineOptions, Registration};
use incontext::{CliError, ErrorKind};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray2};
use pyo3::exceptions::{PyLookupError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

pyo3::create_exception!(
    incontext,
    NotFoundError,
    PyLookupError,
    "The object was not found in the depth map (the command line's exit code 3): segmentation \
     found too few object points, or the best pose explains almost none of the object's depth."
);

/// The Python exception of an engine error: `ValueError` for bad input, `NotFoundError` for
/// an object not found, `RuntimeError` for the rest (a bug or the environment).
fn py_err(e: CliError) -> PyErr {
    match e.kind {
        ErrorKind::Input => PyValueError::new_err(e.message),
        ErrorKind::NotFound => NotFoundError::new_err(e.message),
        ErrorKind::Internal => PyRuntimeError::new_err(format!(
            "internal error (a bug, please report it): {}",
            e.message
        )),
    }
}

fn value_error(message: String) -> PyErr {
    PyValueError::new_err(message)
}

// ---------------------------------------------------------------------------------------------
// Array conversion.

/// A NumPy array, its shape, its dtype's kind (`u`, `i`, `f`, `b`, …), size in bytes and name.
type ArrayInfo<'py> = (Bound<'py, PyAny>, Vec<usize>, char, usize, String);

/// `obj` as a NumPy array (lists and other array-likes are converted), with its shape and its
/// dtype's kind (`u`, `i`, `f`, `b`, …) and size in bytes.
fn as_array<'py>(obj: &Bound<'py, PyAny>, what: &str) -> PyResult<ArrayInfo<'py>> {
    let py = obj.py();
    let np = py.import("numpy")?;
    let arr = np.call_method1("asarray", (obj,)).map_err(|e| {
        value_error(format!(
            "{what}: cannot be read as an array: {}",
            e.value(py)
        ))
    })?;
    let shape: Vec<usize> = arr.getattr("shape")?.extract()?;
    let dtype = arr.getattr("dtype")?;
    let kind: String = dtype.getattr("kind")?.extract()?;
    let itemsize: usize = dtype.getattr("itemsize")?.extract()?;
    let name: String = dtype.getattr("name")?.extract()?;
    Ok((
        arr,
        shape,
        kind.chars().next().unwrap_or('?'),
        itemsize,
        name,
    ))
}

fn shape_text(shape: &[usize]) -> String {
    match shape {
        [n] => format!("({n},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(|n| n.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// The values of a 2-D array converted to the native `dtype` (row-major, whatever the
/// array's memory order).
fn values_2d<T: numpy::Element + Copy>(
    arr: &Bound<'_, PyAny>,
    dtype: &str,
) -> PyResult<(Vec<T>, usize, usize)> {
    let native = arr.call_method1("astype", (dtype,))?;
    let a: PyReadonlyArray2<T> = native.extract()?;
    let view = a.as_array();
    let (rows, cols) = view.dim();
    Ok((view.iter().copied().collect(), rows, cols))
}

/// An image-shaped array: `(H, W)`, or `(H, W, 1)`.
fn image_shape(shape: &[usize], what: &str, expected: &str) -> PyResult<(usize, usize)> {
    match shape {
        [h, w] | [h, w, 1] if *h > 0 && *w > 0 => Ok((*h, *w)),
        [_, _, c] => Err(value_error(format!(
            "{what}: expected {expected} of shape (H, W), got shape {} ({c} channels)",
            shape_text(shape)
        ))),
        _ => Err(value_error(format!(
            "{what}: expected {expected} of shape (H, W), got shape {}",
            shape_text(shape)
        ))),
    }
}

/// Owned depth values of one of the kinds [`DepthValues`] borrows.
enum DepthArray {
    U16(Vec<u16>),
    F32(Vec<f32>),
    F64(Vec<f64>),
}

impl DepthArray {
    fn values(&self) -> DepthValues<'_> {
        match self {
            DepthArray::U16(v) => DepthValues::U16(v),
            DepthArray::F32(v) => DepthValues::F32(v),
            DepthArray::F64(v) => DepthValues::F64(v),
        }
    }
}

/// A depth map: uint16 (as stored in a BOP PNG) and float32 as they are, float64 kept in
/// double precision, float16 and integers of 16 bits or more converted; 8-bit, bool, complex
/// and other dtypes refused.
fn depth_array(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<(DepthArray, u32, u32)> {
    let expected = "a depth map (uint16 or float32, value × depth_scale = mm)";
    let (arr, shape, kind, itemsize, name) = as_array(obj, what)?;
    let (h, w) = image_shape(&shape, what, expected)?;
    let arr = arr.call_method1("reshape", ((h, w),))?;
    let (depth, rows, cols) = match (kind, itemsize) {
        ('u', 2) => {
            let (v, r, c) = values_2d::<u16>(&arr, "uint16")?;
            (DepthArray::U16(v), r, c)
        }
        ('f', 4) | ('f', 2) => {
            let (v, r, c) = values_2d::<f32>(&arr, "float32")?;
            (DepthArray::F32(v), r, c)
        }
        ('f', 8) | ('u', 4 | 8) | ('i', 2 | 4 | 8) => {
            let (v, r, c) = values_2d::<f64>(&arr, "float64")?;
            (DepthArray::F64(v), r, c)
        }
        _ => {
            return Err(value_error(format!(
                "{what}: expected {expected}, got dtype {name}{}",
                if itemsize == 1 && matches!(kind, 'u' | 'i' | 'b') {
                    " (8-bit: is this a mask or an image rather than a depth map?)"
                } else {
                    ""
                }
            )));
        }
    };
    let size = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
    debug_assert_eq!((rows, cols), (h, w));
    Ok((depth, size(cols), size(rows)))
}

/// A mask: bool, or integers (non-zero = object, as in a mask PNG).
fn mask_array(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<(Vec<bool>, u32, u32)> {
    let expected = "an object mask (bool, or integers: non-zero = object)";
    let (arr, shape, kind, _, name) = as_array(obj, what)?;
    let (h, w) = image_shape(&shape, what, expected)?;
    if !matches!(kind, 'b' | 'u' | 'i') {
        return Err(value_error(format!(
            "{what}: expected {expected}, got dtype {name}"
        )));
    }
    let arr = arr.call_method1("reshape", ((h, w),))?;
    let (v, rows, cols) = values_2d::<bool>(&arr, "bool")?;
    let size = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
    Ok((v, size(cols), size(rows)))
}

/// An `(N, columns)` array of real numbers (integers or floats) as f64, row-major; refused when
/// N exceeds `max_rows`.
fn real_rows(
    obj: &Bound<'_, PyAny>,
    what: &str,
    columns: usize,
    max_rows: Option<u64>,
) -> PyResult<(Vec<f64>, usize)> {
    let (arr, shape, kind, _, name) = as_array(obj, what)?;
    if !matches!(kind, 'f' | 'u' | 'i') {
        return Err(value_error(format!(
            "{what}: expected real numbers (float or integer), got dtype {name}"
        )));
    }
    let n = match shape.as_slice() {
        [n, c] if *c == columns => *n,
        _ => {
            return Err(value_error(format!(
                "{what}: expected shape (N, {columns}), got shape {}",
                shape_text(&shape)
            )));
        }
    };
    // Refused on the shape, before the copy.
    if let Some(max) = max_rows.filter(|&max| n as u64 > max) {
        return Err(value_error(format!(
            "{what}: {n} rows is more than the {max} accepted; subsample them"
        )));
    }
    let (v, _, _) = values_2d::<f64>(&arr, "float64")?;
    Ok((v, n))
}

/// A fixed-shape matrix of real numbers (`(rows, cols)`, or `rows·cols` numbers when
/// `flat_ok`), as f64 row-major.
fn real_matrix(
    obj: &Bound<'_, PyAny>,
    what: &str,
    rows: usize,
    cols: usize,
    flat_ok: bool,
) -> PyResult<Vec<f64>> {
    let (arr, shape, kind, _, name) = as_array(obj, what)?;
    if !matches!(kind, 'f' | 'u' | 'i') {
        return Err(value_error(format!(
            "{what}: expected real numbers (float or integer), got dtype {name}"
        )));
    }
    let ok = shape == [rows, cols] || (flat_ok && shape == [rows * cols]);
    if !ok {
        return Err(value_error(format!(
            "{what}: expected shape ({rows}, {cols}){}, got shape {}",
            if flat_ok {
                format!(" or ({},)", rows * cols)
            } else {
                String::new()
            },
            shape_text(&shape)
        )));
    }
    let arr = arr.call_method1("reshape", ((rows, cols),))?;
    let (v, _, _) = values_2d::<f64>(&arr, "float64")?;
    Ok(v)
}

fn vec3s(values: &[f64]) -> Vec<Vec3> {
    values
        .chunks_exact(3)
        .map(|c| Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32))
        .collect()
}

fn bool_image<'py>(
    py: Python<'py>,
    width: u32,
    height: u32,
    data: Vec<bool>,
) -> PyResult<Bound<'py, PyArray2<bool>>> {
    let a = Array2::from_shape_vec((height as usize, width as usize), data)
        .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py))
}

// ---------------------------------------------------------------------------------------------
// Model.

/// A known object's mesh, in its own units (`unit_mm` millimetres each: 1 for BOP meshes in
/// mm, 1000 for meshes in metres).
///
/// `Model.from_file(path, unit_mm=1.0)` reads an OBJ, PLY, OFF or glTF/GLB file;
/// `Model(vertices, faces, unit_mm=1.0)` takes a (V, 3) array of vertex coordinates (mesh
/// units, float or integer) and an (F, 3) array of triangles (integer vertex indices).
/// The points the engine registers are sampled from the mesh once per seed and kept.
#[pyclass(module = "incontext", frozen)]
struct Model {
    mesh: Arc<Mesh>,
    unit_mm: f64,
    source: String,
    /// Sampled objects by seed (the few last used).
    objects: Mutex<Vec<(u64, Arc<Object>)>>,
}

impl Model {
    fn build(mesh: Mesh, unit_mm: f64, source: String) -> PyResult<Model> {
        arrays::check_unit_mm(unit_mm, "unit_mm").map_err(py_err)?;
        Ok(Model {
            mesh: Arc::new(mesh),
            unit_mm,
            source,
            objects: Mutex::new(Vec::new()),
        })
    }

    /// The object sampled with `seed` (as `incontext register --seed` samples it), and the
    /// seconds spent sampling it now (0 when it was kept from an earlier call).
    fn object(&self, seed: u64) -> Result<(Arc<Object>, f64), CliError> {
        let mut cache = self
            .objects
            .lock()
            .map_err(|_| CliError::internal("a registration panicked while sampling the model"))?;
        if let Some((_, o)) = cache.iter().find(|(s, _)| *s == seed) {
            return Ok((o.clone(), 0.0));
        }
        let object = Arc::new(
            Object::from_mesh((*self.mesh).clone(), seed).map_err(|e| e.context(&self.source))?,
        );
        let seconds = object.seconds;
        if cache.len() >= 4 {
            cache.remove(0);
        }
        cache.push((seed, object.clone()));
        Ok((object, seconds))
    }
}

#[pymethods]
impl Model {
    #[new]
    #[pyo3(signature = (vertices, faces, unit_mm = 1.0))]
    fn new(vertices: &Bound<'_, PyAny>, faces: &Bound<'_, PyAny>, unit_mm: f64) -> PyResult<Self> {
        let (v, _) = real_rows(vertices, "vertices", 3, None)?;
        let (f_arr, shape, kind, _, name) = as_array(faces, "faces")?;
        if !matches!(kind, 'u' | 'i') {
            return Err(value_error(format!(
                "faces: expected integer vertex indices, got dtype {name}"
            )));
        }
        if !matches!(shape.as_slice(), [_, 3]) {
            return Err(value_error(format!(
                "faces: expected shape (F, 3), got shape {}",
                shape_text(&shape)
            )));
        }
        let (idx, _, _) = values_2d::<i64>(&f_arr, "int64")?;
        let mut triangles = Vec::with_capacity(idx.len() / 3);
        for (face, c) in idx.chunks_exact(3).enumerate() {
            let mut t = [0u32; 3];
            for (k, &i) in c.iter().enumerate() {
                t[k] = u32::try_from(i).map_err(|_| {
                    value_error(format!(
                        "faces: face {face} refers to vertex {i}, but the mesh has {} vertices",
                        v.len() / 3
                    ))
                })?;
            }
            triangles.push(t);
        }
        let mesh = arrays::mesh(vec3s(&v), triangles, "Model(vertices, faces)").map_err(py_err)?;
        Model::build(mesh, unit_mm, "Model(vertices, faces)".into())
    }

    /// Reads a mesh file (OBJ, PLY, OFF, glTF/GLB) in its own units, `unit_mm` mm each.
    #[staticmethod]
    #[pyo3(signature = (path, unit_mm = 1.0))]
    fn from_file(py: Python<'_>, path: PathBuf, unit_mm: f64) -> PyResult<Self> {
        arrays::check_unit_mm(unit_mm, "unit_mm").map_err(py_err)?;
        let mesh = py.detach(|| inputs::read_mesh(&path)).map_err(py_err)?;
        Model::build(mesh, unit_mm, path.display().to_string())
    }

    /// The vertices, (V, 3) float32, in the mesh's units.
    #[getter]
    fn vertices<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let data: Vec<f32> = self
            .mesh
            .vertices
            .iter()
            .flat_map(|v| v.to_array())
            .collect();
        let a = Array2::from_shape_vec((self.mesh.vertices.len(), 3), data)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py))
    }

    /// The triangles, (F, 3) int64 vertex indices.
    #[getter]
    fn faces<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<i64>>> {
        let data: Vec<i64> = self
            .mesh
            .triangles
            .iter()
            .flat_map(|t| t.map(|i| i as i64))
            .collect();
        let a = Array2::from_shape_vec((self.mesh.triangles.len(), 3), data)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py))
    }

    /// Millimetres per mesh unit.
    #[getter]
    fn unit_mm(&self) -> f64 {
        self.unit_mm
    }

    fn __repr__(&self) -> String {
        format!(
            "Model({:?}: {} vertices, {} triangles, unit_mm={})",
            self.source,
            self.mesh.vertices.len(),
            self.mesh.triangles.len(),
            self.unit_mm
        )
    }
}

// ---------------------------------------------------------------------------------------------
// Camera.

/// A pinhole camera: `K` (3, 3) in pixels (`[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`, or the
/// 9 numbers row-major like BOP's cam_K), the image size in pixels, and the depth scale of
/// the sensor's values (`value × depth_scale = mm`, BOP; 1 for depth in mm). Checked like a
/// camera file of `incontext register`.
#[pyclass(module = "incontext", frozen)]
struct Camera {
    file: CameraFile,
}

fn image_side(v: i64, name: &str) -> PyResult<u64> {
    u64::try_from(v)
        .map_err(|_| value_error(format!("camera: {name}: {v} is not a positive image size")))
}

#[pymethods]
impl Camera {
    #[new]
    #[pyo3(signature = (K, width, height, depth_scale = 1.0))]
    #[allow(non_snake_case)]
    fn new(K: &Bound<'_, PyAny>, width: i64, height: i64, depth_scale: f64) -> PyResult<Self> {
        let k = real_matrix(K, "camera: K", 3, 3, true)?;
        let k: [f64; 9] = k
            .try_into()
            .map_err(|_| PyRuntimeError::new_err("K has 9 entries"))?;
        let file = arrays::camera(
            k,
            image_side(width, "width")?,
            image_side(height, "height")?,
            depth_scale,
            "camera",
        )
        .map_err(py_err)?;
        Ok(Camera { file })
    }

    /// Reads a camera JSON as `incontext register --camera` does (cam_K or fx, fy, cx, cy;
    /// width, height; depth_scale); `width` and `height` are needed when the file has none.
    #[staticmethod]
    #[pyo3(signature = (path, width = None, height = None))]
    fn from_file(path: PathBuf, width: Option<u32>, height: Option<u32>) -> PyResult<Self> {
        let file = inputs::read_camera(&path, || match (width, height) {
            (Some(w), Some(h)) => Ok((w, h)),
            _ => Err(CliError::input(format!(
                "{}: no width and height in the camera file: pass width= and height=",
                path.display()
            ))),
        })
        .map_err(py_err)?;
        Ok(Camera { file })
    }

    /// The intrinsic matrix, (3, 3) float64, pixels.
    #[getter]
    #[allow(non_snake_case)]
    fn K<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let rows = self.file.intrinsics.k_row_major();
        let a = Array2::from_shape_vec((3, 3), rows.concat())
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py))
    }

    #[getter]
    fn width(&self) -> u32 {
        self.file.intrinsics.width
    }

    #[getter]
    fn height(&self) -> u32 {
        self.file.intrinsics.height
    }

    /// `value × depth_scale = mm`.
    #[getter]
    fn depth_scale(&self) -> f64 {
        self.file.depth_scale
    }

    fn __repr__(&self) -> String {
        let k = &self.file.intrinsics;
        format!(
            "Camera(fx={}, fy={}, cx={}, cy={}, width={}, height={}, depth_scale={})",
            k.fx, k.fy, k.cx, k.cy, k.width, k.height, self.file.depth_scale
        )
    }
}

// ---------------------------------------------------------------------------------------------
// Registrar and Result.

fn parse_head(s: &str) -> PyResult<ic_pose::Head> {
    incontext::register::parse_head(s).map_err(|e| value_error(format!("head: {e}")))
}

fn parse_refine(s: &str) -> PyResult<ic_pose::Refine> {
    incontext::register::parse_refine(s).map_err(|e| value_error(format!("refine: {e}")))
}

/// The registration engine: the shipped (or given) networks and the settings of
/// `incontext register` (the same defaults and flags), with a seed for every random choice.
///
/// `head`: the pose network's correspondence head, "softmax" or "ot" (None: the checkpoint's
/// own); `refine`: "icp" or "none"; `threads`: compute threads (None: all logical CPUs);
/// `seed`: the seed of every random choice (`incontext register --seed`); `rotations`,
/// `hypotheses`, `verify_top`: as the flags of `incontext register`; `pose_model`,
/// `seg_model`: checkpoints instead of the shipped networks (a `pose_model` or `seg_model` is
/// then the only one of its kind: no second pose network, no one-object second opinion);
/// `second_pose_model`: a second pose checkpoint whose hypotheses join the main network's in
/// verification, instead of the shipped one; `second_pose=False`: the main network alone
/// (`register --no-second-pose`).
#[pyclass(module = "incontext", frozen)]
struct Registrar {
    /// Without the segmentation network: used when a mask is given (as the command line).
    bare: Pipeline,
    /// With it: used without a mask; `None` when it is neither shipped nor given.
    segmenting: Option<Pipeline>,
    pool: Option<rayon::ThreadPool>,
    seed: u64,
    threads: Option<usize>,
}

impl Registrar {
    fn run<T: Send>(&self, f: impl FnOnce() -> T + Send) -> T {
        match &self.pool {
            Some(pool) => pool.install(f),
            None => f(),
        }
    }

    fn pipeline(&self, with_mask: bool) -> Result<&Pipeline, CliError> {
        if with_mask {
            return Ok(&self.bare);
        }
        self.segmenting.as_ref().ok_or_else(|| {
            CliError::input(format!(
                "the segmentation model models/{} is not built into this module and {} does not \
                 exist: pass seg_model=FILE to Registrar, or give a mask",
                incontext::models::SEG.file,
                incontext::models::SEG.workspace_path().display()
            ))
        })
    }
}

/// `attention_keys=`: an int ≥ 1 (keys per cloud) or "all" (every point).
fn parse_attention_keys(v: &Bound<'_, PyAny>) -> PyResult<Option<usize>> {
    if let Ok(s) = v.extract::<String>() {
        return incontext::register::parse_attention_keys(&s)
            .map(|k| k.0)
            .map_err(|e| value_error(format!("attention_keys: {e}")));
    }
    match v.extract::<i64>() {
        Ok(n) if n >= 1 => Ok(Some(n as usize)),
        _ => Err(value_error(format!(
            "attention_keys: {v} is not a number of keys (an int ≥ 1, or \"all\")"
        ))),
    }
}

#[pymethods]
impl Registrar {
    #[new]
    #[pyo3(signature = (head = Some("softmax"), refine = "icp", threads = None, seed = 0, *, rotations = 24, hypotheses = 1, verify_top = 8, pose_model = None, seg_model = None, second_pose_model = None, second_pose = true, attention_keys = None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        head: Option<&str>,
        refine: &str,
        threads: Option<i64>,
        seed: u64,
        rotations: usize,
        hypotheses: u32,
        verify_top: u32,
        pose_model: Option<PathBuf>,
        seg_model: Option<PathBuf>,
        second_pose_model: Option<PathBuf>,
        second_pose: bool,
        attention_keys: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let attention_keys = attention_keys.map(parse_attention_keys).transpose()?;
        if !second_pose && second_pose_model.is_some() {
            return Err(value_error(
                "second_pose_model is given but second_pose is False".into(),
            ));
        }
        let head = head.map(parse_head).transpose()?;
        let refine = parse_refine(refine)?;
        incontext::register::parse_rotations(&rotations.to_string())
            .map_err(|e| value_error(format!("rotations: {e}")))?;
        if !(1..=64).contains(&hypotheses) {
            return Err(value_error(format!(
                "hypotheses: {hypotheses} is not in 1..=64"
            )));
        }
        if !(1..=60).contains(&verify_top) {
            return Err(value_error(format!(
                "verify_top: {verify_top} is not in 1..=60"
            )));
        }
        let threads = match threads {
            None => None,
            Some(t) if t >= 1 => {
                let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
                Some((t as usize).min(cpus))
            }
            Some(t) => {
                return Err(value_error(format!(
                    "threads: {t} is not a number of threads (at least 1, or None for all CPUs)"
                )));
            }
        };
        // The options of `incontext register` (NetworkArgs::pipeline) with its flags' defaults.
        let options = PipelineOptions {
            refine,
            hypotheses: hypotheses as usize,
            rotations,
            verify_top: verify_top as usize,
            ..PipelineOptions::default()
        };
        let with_seg = seg_model.is_some() || incontext::models::SEG.available();
        let (bare, segmenting) = py
            .detach(|| -> Result<_, CliError> {
                let mut builder = Pipeline::builder()
                    .options(options)
                    .second_pose(second_pose);
                if let Some(path) = &second_pose_model {
                    builder = builder.second_pose_model(path);
                }
                if let Some(head) = head {
                    builder = builder.head(head);
                }
                if let Some(path) = &pose_model {
                    builder = builder.pose_model(path);
                }
                if let Some(keys) = attention_keys {
                    builder = builder.attention_keys(keys);
                }
                let bare = builder.clone().segmentation(false).build()?;
                let segmenting = if with_seg {
                    if let Some(path) = &seg_model {
                        builder = builder.seg_model(path);
                    }
                    Some(builder.segmentation(true).build()?)
                } else {
                    None
                };
                Ok((bare, segmenting))
            })
            .map_err(py_err)?;
        let pool = match threads {
            Some(t) => Some(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .map_err(|e| PyRuntimeError::new_err(format!("starting {t} threads: {e}")))?,
            ),
            None => None,
        };
        Ok(Registrar {
            bare,
            segmenting,
            pool,
            seed,
            threads,
        })
    }

    /// Registers `model` in one depth map.
    ///
    /// `depth`: (H, W) uint16 or float32 (other integer and float types are converted), the
    /// sensor's values: `value × camera.depth_scale = mm`, 0 = no return. `mask`: optional
    /// (H, W) bool (or integers, non-zero = object) of the object's pixels instead of the
    /// segmentation network. Raises ValueError on bad input and NotFoundError when the object
    /// is not found. The GIL is released while the engine runs.
    #[pyo3(signature = (model, depth, camera, mask = None))]
    fn register(
        &self,
        py: Python<'_>,
        model: &Bound<'_, Model>,
        depth: &Bound<'_, PyAny>,
        camera: &Bound<'_, Camera>,
        mask: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<RegistrationResult> {
        let clock = Instant::now();
        let (values, w, h) = depth_array(depth, "depth")?;
        let mask = mask.map(|m| mask_array(m, "mask")).transpose()?;
        let model = model.get();
        let camera = camera.get().file;
        let seed = self.seed;
        let (r, model_seconds) = py
            .detach(|| {
                self.run(|| -> Result<(Registration, f64), CliError> {
                    let depth_mm = arrays::depth_mm(values.values(), w, h, &camera, "depth")?;
                    let k = camera.intrinsics;
                    let mask = match mask {
                        Some((m, mw, mh)) => Some(arrays::mask(m, mw, mh, &k, "mask")?),
                        None => None,
                    };
                    let pipeline = self.pipeline(mask.is_some())?;
                    let (object, seconds) = model.object(seed)?;
                    let r = arrays::register_depth_mm(
                        pipeline,
                        &object,
                        &depth_mm,
                        &k,
                        mask.as_ref(),
                        model.unit_mm,
                        seed,
                    )?;
                    Ok((r, seconds))
                })
            })
            .map_err(py_err)?;
        Ok(RegistrationResult::new(
            &r,
            model.unit_mm,
            model_seconds,
            clock.elapsed().as_secs_f64(),
        ))
    }

    /// Registers `model` onto observed points of the object: (N, 3) float, camera frame
    /// (x right, y down, z forward), in millimetres. No segmentation. Raises ValueError on
    /// bad input and NotFoundError when the object is not found.
    fn register_points(
        &self,
        py: Python<'_>,
        model: &Bound<'_, Model>,
        points: &Bound<'_, PyAny>,
    ) -> PyResult<RegistrationResult> {
        let clock = Instant::now();
        // No depth map the readers accept gives more points than it has pixels.
        let (p, _) = real_rows(points, "points", 3, Some(ic_render::io::MAX_IMAGE_PIXELS))?;
        let points = vec3s(&p);
        let model = model.get();
        let seed = self.seed;
        let (r, model_seconds) = py
            .detach(|| {
                self.run(|| -> Result<(Registration, f64), CliError> {
                    let (object, seconds) = model.object(seed)?;
                    let r = arrays::register_points_mm(
                        &self.bare,
                        &object,
                        &points,
                        model.unit_mm,
                        seed,
                    )?;
                    Ok((r, seconds))
                })
            })
            .map_err(py_err)?;
        Ok(RegistrationResult::new(
            &r,
            model.unit_mm,
            model_seconds,
            clock.elapsed().as_secs_f64(),
        ))
    }

    #[getter]
    fn seed(&self) -> u64 {
        self.seed
    }

    /// Compute threads (None: all logical CPUs).
    #[getter]
    fn threads(&self) -> Option<usize> {
        self.threads
    }

    fn __repr__(&self) -> String {
        format!(
            "Registrar(pose_model={:?}, second_pose_model={:?}, seg_model={:?}, seed={}, threads={:?}, options={:?})",
            self.bare.pose_source(),
            self.bare.second_pose_source(),
            self.segmenting.as_ref().and_then(|p| p.seg_source()),
            self.seed,
            self.threads,
            self.bare.options
        )
    }
}

/// One registration: the pose of the model in the camera frame (x right, y down, z forward;
/// `x_cam = R·x + t`, `t` in millimetres), how far it can be trusted, the time of each stage.
#[pyclass(module = "incontext", name = "Result", frozen)]
struct RegistrationResult {
    rotation: [[f64; 3]; 3],
    /// Millimetres.
    translation: DVec3,
    confidence: f64,
    calibration: &'static str,
    verdict: &'static str,
    /// (stage, milliseconds).
    timings: Vec<(&'static str, f64)>,
    mask: Option<(u32, u32, Vec<bool>)>,
    object_voxels: usize,
    verification: Option<incontext::verify::Score>,
    whole_view: Option<incontext::verify::WholeView>,
}

impl RegistrationResult {
    fn new(r: &Registration, unit_mm: f64, model_seconds: f64, total_seconds: f64) -> Self {
        let s = &r.seconds;
        let ms = |x: f64| x * 1e3;
        RegistrationResult {
            rotation: r.pose.rotation_row_major(),
            // As BOP's cam_t_m2c of `incontext register`.
            translation: r.pose.translation * unit_mm,
            confidence: r.confidence,
            calibration: r.calibration.as_str(),
            verdict: r.verdict.as_str(),
            timings: vec![
                ("model_points", ms(model_seconds)),
                ("segmentation_network", ms(s.segmentation_network)),
                ("segmentation_post", ms(s.segmentation_post)),
                ("observed_points", ms(s.observed_points)),
                ("pose_network", ms(s.pose_network)),
                ("ranking", ms(s.ranking)),
                ("icp", ms(s.icp)),
                ("verification", ms(s.verification)),
                ("registration", ms(s.total)),
                ("total", ms(total_seconds)),
            ],
            mask: r.mask.as_ref().map(|m| (m.width, m.height, m.data.clone())),
            object_voxels: r.object_voxels,
            verification: r.verification,
            whole_view: r.whole_view,
        }
    }
}

#[pymethods]
impl RegistrationResult {
    /// Rotation, model → camera, (3, 3) float64.
    #[getter(R)]
    fn rotation<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let a = Array2::from_shape_vec((3, 3), self.rotation.concat())
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py))
    }

    /// Translation, model → camera, (3,) float64, millimetres.
    #[getter(t)]
    fn translation<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.translation.to_array().to_vec().into_pyarray(py)
    }

    /// The 4 × 4 homogeneous transform `[[R, t], [0, 0, 0, 1]]` (float64, t in millimetres).
    #[getter(T)]
    fn transform<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let (r, t) = (&self.rotation, self.translation);
        let data = vec![
            r[0][0], r[0][1], r[0][2], t.x, r[1][0], r[1][1], r[1][2], t.y, r[2][0], r[2][1],
            r[2][2], t.z, 0.0, 0.0, 0.0, 1.0,
        ];
        let a = Array2::from_shape_vec((4, 4), data)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py))
    }

    /// In [0, 1]: the calibrated probability that the pose is right (verified registrations,
    /// the default), or the fraction of the object's points the pose explains (rotations=1).
    #[getter]
    fn confidence(&self) -> f64 {
        self.confidence
    }

    /// Which calibration gave the confidence: "object" (a mask was given, or the segmentation
    /// found one instance only), "segmentation" (the network chose among several instances;
    /// calibrated on cluttered scenes, where a good fit may be another object), or "none"
    /// (rotations=1: not a probability).
    #[getter]
    fn calibration(&self) -> &'static str {
        self.calibration
    }

    /// "ok" (use the pose) or "uncertain" (check it); "not_found" raises NotFoundError.
    #[getter]
    fn verdict(&self) -> &'static str {
        self.verdict
    }

    /// Milliseconds per stage (as `timings_ms` of `incontext register`; `total` is the
    /// whole call).
    #[getter]
    fn timings<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (k, v) in &self.timings {
            d.set_item(*k, *v)?;
        }
        Ok(d)
    }

    /// The object's pixels used, (H, W) bool (the given mask or the segmentation's); None
    /// for `register_points`.
    #[getter]
    fn mask<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<bool>>>> {
        self.mask
            .as_ref()
            .map(|(w, h, data)| bool_image(py, *w, *h, data.clone()))
            .transpose()
    }

    /// Object voxels the pose was estimated from.
    #[getter]
    fn object_voxels(&self) -> usize {
        self.object_voxels
    }

    /// The render-and-compare scores of the pose, as `details.verification` of `incontext
    /// register --json` (each in [0, 1]): `score` (coverage × (1 − 3·violation)), `coverage`
    /// (share of the object's pixels the model explains), `agreement` (share of the model's
    /// rendered pixels that agree with the depth), `visible_agreement` (the same among those
    /// not hidden behind a nearer observed surface), `violation` (share in front of the
    /// observed surface), `misfit` (mean depth residual of the agreeing pixels in units of
    /// their tolerance: near 0 when the surface fits within the sensor noise). None when the
    /// pose was not verified (rotations=1).
    #[getter]
    fn verification<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some(v) = self.verification else {
            return Ok(None);
        };
        let d = PyDict::new(py);
        d.set_item("score", v.score)?;
        d.set_item("coverage", v.coverage)?;
        d.set_item("agreement", v.agreement)?;
        d.set_item("violation", v.violation)?;
        d.set_item("visible_agreement", v.visible_agreement)?;
        d.set_item("misfit", v.misfit)?;
        Ok(Some(d))
    }

    /// The model rendered at the pose over the whole image against the depth map, as
    /// `details.whole_view` of `incontext register --json`: `rendered_pixels`,
    /// `visible_pixels` (not hidden behind a nearer observed surface), and the shares of the
    /// visible ones that `agreement` (agree with the depth), lie `in_front` of the observed
    /// surface, or are `missing` (no return). None for point inputs.
    #[getter]
    fn whole_view<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some(w) = self.whole_view else {
            return Ok(None);
        };
        let d = PyDict::new(py);
        d.set_item("rendered_pixels", w.rendered_pixels)?;
        d.set_item("visible_pixels", w.visible_pixels)?;
        d.set_item("agreement", w.agreement)?;
        d.set_item("in_front", w.in_front)?;
        d.set_item("missing", w.missing)?;
        Ok(Some(d))
    }

    /// The pose as BOP writes it: {"cam_R_m2c": 9 floats (row-major), "cam_t_m2c": 3 floats
    /// (mm)}.
    fn to_bop<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        d.set_item("cam_R_m2c", PyList::new(py, self.rotation.concat())?)?;
        d.set_item("cam_t_m2c", PyList::new(py, self.translation.to_array())?)?;
        Ok(d)
    }

    fn __repr__(&self) -> String {
        let t = self.translation;
        format!(
            "Result(verdict={:?}, confidence={:.3}, t=[{:.3}, {:.3}, {:.3}] mm, R={:?})",
            self.verdict, self.confidence, t.x, t.y, t.z, self.rotation
        )
    }
}

// ---------------------------------------------------------------------------------------------
// Functions.

/// A depth map and a mask.
type DepthAndMask<'py> = (Bound<'py, PyArray2<f32>>, Bound<'py, PyArray2<bool>>);

/// Renders `model` at `pose` (a (4, 4) model → camera transform with t in millimetres, or a
/// Result) through `camera`: returns (depth, mask), depth (H, W) float32 in the sensor's
/// units (`value × camera.depth_scale = mm`, 0 = no return) and mask (H, W) bool (the
/// model's pixels). As `incontext render`.
#[pyfunction]
fn render<'py>(
    py: Python<'py>,
    model: &Bound<'py, Model>,
    pose: &Bound<'py, PyAny>,
    camera: &Bound<'py, Camera>,
) -> PyResult<DepthAndMask<'py>> {
    let pose = if let Ok(r) = pose.cast::<RegistrationResult>() {
        r.get().transform(py)?.into_any()
    } else {
        pose.clone()
    };
    let m = real_matrix(&pose, "pose", 4, 4, false)?;
    let model = model.get();
    let file = camera.get().file;
    if m[12..15].iter().any(|&x| x != 0.0) || m[15] != 1.0 {
        return Err(value_error(format!(
            "pose: the bottom row is [{}, {}, {}, {}], expected [0, 0, 0, 1]",
            m[12], m[13], m[14], m[15]
        )));
    }
    let rows = [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]];
    let to_units = 1.0 / model.unit_mm;
    let t = [m[3] * to_units, m[7] * to_units, m[11] * to_units];
    let pose = Pose::from_row_major(rows, t)
        .map(|p| p.orthonormalised())
        .map_err(|e| value_error(format!("pose: {e}")))?;
    let (depth, mask) = py
        .detach(|| -> Result<_, CliError> {
            use ic_render::{Camera as RenderCamera, CpuRenderer, Renderer, Scene};
            let scene = Scene::single(model.mesh.clone(), Pose::IDENTITY, 1);
            let mut cam = RenderCamera::new(file.intrinsics, pose);
            // Near plane: 1 mm in mesh units (as `incontext render`).
            cam.near = to_units;
            let view = CpuRenderer::new().render(&scene, &cam)?;
            let mask = view.mask(1);
            let to_sensor = model.unit_mm / file.depth_scale;
            let depth: Vec<f32> = view
                .depth
                .data
                .iter()
                .map(|&z| (z as f64 * to_sensor) as f32)
                .collect();
            Ok((depth, mask))
        })
        .map_err(py_err)?;
    let (w, h) = (mask.width as usize, mask.height as usize);
    let depth = Array2::from_shape_vec((h, w), depth)
        .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    Ok((
        depth.into_pyarray(py),
        bool_image(py, mask.width, mask.height, mask.data)?,
    ))
}

/// Reads a 16-bit grayscale PNG (a BOP depth map) as its stored values: (H, W) uint16
/// (`value × depth_scale = mm` with the scene's depth_scale). Raises ValueError naming the
/// file when it is missing or not a 16-bit grayscale PNG.
#[pyfunction]
fn read_depth_png<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyArray2<u16>>> {
    let image = py
        .detach(|| ic_render::io::read_instances_png(&path, None))
        .map_err(|e| py_err(e.into()))?;
    // 16-bit values read as u32: every one fits u16.
    let data: Vec<u16> = image
        .data
        .iter()
        .map(|&v| v.min(u16::MAX as u32) as u16)
        .collect();
    let a = Array2::from_shape_vec((image.height as usize, image.width as usize), data)
        .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py))
}

/// Reads an 8-bit grayscale mask PNG: (H, W) bool, non-zero = object. Raises ValueError
/// naming the file when it is missing or not an 8-bit grayscale PNG.
#[pyfunction]
fn read_mask_png<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyArray2<bool>>> {
    let mask = py
        .detach(|| ic_render::io::read_mask_png(&path, None))
        .map_err(|e| py_err(e.into()))?;
    bool_image(py, mask.width, mask.height, mask.data)
}

#[pymodule]
fn _incontext(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Model>()?;
    m.add_class::<Camera>()?;
    m.add_class::<Registrar>()?;
    m.add_class::<RegistrationResult>()?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    m.add_function(wrap_pyfunction!(read_depth_png, m)?)?;
    m.add_function(wrap_pyfunction!(read_mask_png, m)?)?;
    m.add("NotFoundError", m.py().get_type::<NotFoundError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}

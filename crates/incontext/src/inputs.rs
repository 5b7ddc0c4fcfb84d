//! Reading the user's files with checks: cameras (BOP-style JSON), depth maps (16-bit PNG or
//! EXR), masks, meshes and poses. Every error is bad input (exit code 2) and names the file.

use std::path::Path;

use ic_geometry::{DepthImage, Image, Intrinsics, Mask, Mesh, Pose};
use serde_json::Value;

use crate::error::{CliError, Result};

/// A camera file: intrinsics, the BOP depth scale (`stored PNG value × depth_scale = mm`) and,
/// for cases exported by `cargo xtask export-cases`, the millimetres per scene unit.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct CameraFile {
    pub intrinsics: Intrinsics,
    pub depth_scale: f64,
    /// Whether width and height came from the file (else from the depth map).
    pub size_given: bool,
    pub unit_mm: Option<f64>,
}

fn bad(path: &Path, message: impl std::fmt::Display) -> CliError {
    CliError::input(format!("{}: {message}", path.display()))
}

/// The largest JSON file read (camera, pose, case ground truth): 64 MiB, far above any real
/// one (a BOP `scene_camera.json` of 1000 images is ≈ 300 kB).
pub const MAX_JSON_BYTES: u64 = 64 << 20;

/// The farthest depth accepted, in mm (10 km). Finite values beyond it (e.g. a renderer's
/// 3e38 background marker) are read as missing returns.
pub const MAX_DEPTH_MM: f32 = 1e7;

/// Reads and parses a JSON file (a regular file of at most [`MAX_JSON_BYTES`]).
pub fn read_json(path: &Path, what: &str) -> Result<Value> {
    let bytes = ic_geometry::io::read_bounded(path, MAX_JSON_BYTES)
        .map_err(|e| bad(path, format!("cannot read the {what}: {e}")))?;
    let text = std::str::from_utf8(&bytes)
        .map_err(|e| bad(path, format!("the {what} is not UTF-8 text: {e}")))?;
    serde_json::from_str(text).map_err(|e| bad(path, format!("the {what} is not valid JSON: {e}")))
}

fn number(v: &Value, path: &Path, key: &str) -> Result<f64> {
    v.as_f64()
        .filter(|x| x.is_finite())
        .ok_or_else(|| bad(path, format!("{key}: {v} is not a finite number")))
}

/// A flat list of numbers from `[a, b, …]` or `[[a, b], [c, d], …]`.
fn flat_numbers(v: &Value, path: &Path, key: &str) -> Result<Vec<f64>> {
    let arr = v
        .as_array()
        .ok_or_else(|| bad(path, format!("{key}: expected a list of numbers")))?;
    let mut out = Vec::new();
    for x in arr {
        match x.as_array() {
            Some(row) => {
                for y in row {
                    out.push(number(y, path, key)?);
                }
            }
            None => out.push(number(x, path, key)?),
        }
    }
    Ok(out)
}

fn size_field(v: &Value, path: &Path, key: &str) -> Result<Option<u32>> {
    match v.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(x) => x
            .as_u64()
            .filter(|&n| n > 0 && n <= 65_535)
            .map(|n| Some(n as u32))
            .ok_or_else(|| bad(path, format!("{key}: {x} is not a positive image size"))),
    }
}

/// `cam_K` must be a pinhole matrix `[fx, 0, cx; 0, fy, cy; 0, 0, 1]`: skew and a bottom row
/// other than `[0, 0, 1]` are refused rather than dropped (the pipeline's projection has
/// neither). Entries within 1e-9 (relative to the focal length) of the expected zeros pass.
fn check_k_shape(k: &[f64], path: &Path) -> Result<()> {
    let scale = k[0].abs().max(k[4].abs()).max(1.0);
    let zero = |x: f64| x.abs() <= 1e-9 * scale;
    if !zero(k[1]) {
        return Err(bad(
            path,
            format!(
                "cam_K has skew (row 0, column 1 = {}): only zero skew is supported; \
                 undistort and rectify the depth map first",
                k[1]
            ),
        ));
    }
    if !zero(k[3]) {
        return Err(bad(
            path,
            format!(
                "cam_K row 1, column 0 is {}, expected 0 (cam_K is [fx, 0, cx, 0, fy, cy, 0, 0, 1], row-major)",
                k[3]
            ),
        ));
    }
    if !(k[6].abs() <= 1e-9 && k[7].abs() <= 1e-9 && (k[8] - 1.0).abs() <= 1e-9) {
        return Err(bad(
            path,
            format!(
                "cam_K's bottom row is [{}, {}, {}], expected [0, 0, 1] (cam_K is row-major; \
                 is it transposed, or a projection matrix?)",
                k[6], k[7], k[8]
            ),
        ));
    }
    Ok(())
}

/// Checks that intrinsics describe a plausible pinhole camera for an image of `width ×
/// height` pixels (`size_given`: the size came from the camera file; else from the depth map):
/// - the image fits the reader's limits ([`ic_render::io::check_image_size`]);
/// - each field of view lies between 0.05° and 170° (focal lengths are in pixels: a
///   640-pixel-wide Kinect has fx ≈ 525);
/// - fx / fy lies within [1/4, 4] (pixels are nearly square on every depth sensor);
/// - the principal point lies within the image extended by half its size on each side; when
///   the size came from the depth map, within the middle half of it (far from the centre means
///   the intrinsics belong to another resolution).
pub fn check_intrinsics(
    path: &Path,
    spec: &CameraSpec,
    width: u32,
    height: u32,
    size_given: bool,
) -> Result<()> {
    let (w, h) = (width as f64, height as f64);
    if ic_render::io::check_image_size(path, width as u64, height as u64).is_err() {
        return Err(bad(
            path,
            format!(
                "the image size {width}×{height} is larger than the largest supported ({} per side, {} pixels in all)",
                ic_render::io::MAX_IMAGE_SIDE,
                ic_render::io::MAX_IMAGE_PIXELS
            ),
        ));
    }
    let fov = |f: f64, side: f64| 2.0 * (side / (2.0 * f)).atan().to_degrees();
    for (name, f, side, axis) in [
        ("fx", spec.fx, w, "horizontal"),
        ("fy", spec.fy, h, "vertical"),
    ] {
        let deg = fov(f, side);
        if !(0.05..=170.0).contains(&deg) {
            return Err(bad(
                path,
                format!(
                    "{name} = {f} pixels gives a {axis} field of view of {deg:.3}° over {side} pixels \
                     (expected 0.05°–170°): focal lengths are in pixels (a 640-pixel-wide Kinect has fx ≈ 525)"
                ),
            ));
        }
    }
    let ratio = spec.fx / spec.fy;
    if !(0.25..=4.0).contains(&ratio) {
        return Err(bad(
            path,
            format!(
                "fx / fy = {ratio:.3} (fx = {}, fy = {}): depth sensors have nearly square pixels; \
                 are fx and fy in the same units?",
                spec.fx, spec.fy
            ),
        ));
    }
    let (cx, cy) = (spec.cx, spec.cy);
    if size_given {
        if !((-0.5 * w..=1.5 * w).contains(&cx) && (-0.5 * h..=1.5 * h).contains(&cy)) {
            return Err(bad(
                path,
                format!(
                    "the principal point ({cx}, {cy}) lies far outside the {width}×{height} image \
                     (cx, cy are in pixels, measured from the top-left corner)"
                ),
            ));
        }
    } else if (cx - (w - 1.0) / 2.0).abs() > w / 4.0 || (cy - (h - 1.0) / 2.0).abs() > h / 4.0 {
        return Err(bad(
            path,
            format!(
                "the principal point ({cx}, {cy}) lies far from the centre of the {width}×{height} \
                 depth map: the intrinsics are probably for another image size; give width and \
                 height in the camera file"
            ),
        ));
    }
    Ok(())
}

/// The fields of a camera JSON.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraSpec {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub size: Option<(u32, u32)>,
    pub depth_scale: f64,
    pub unit_mm: Option<f64>,
}

/// Parses a camera JSON: `cam_K` (9 numbers row-major, or 3×3) or `fx`, `fy`, `cx`, `cy`;
/// `width`, `height` (optional: then the depth map's size is used); `depth_scale` (default
/// 1.0); `unit_mm` (optional). A BOP `scene_camera.json` entry or `camera.json` both work.
pub fn parse_camera(v: &Value, path: &Path) -> Result<CameraSpec> {
    if !v.is_object() {
        return Err(bad(
            path,
            "expected a JSON object with cam_K (or fx, fy, cx, cy)",
        ));
    }
    let (fx, fy, cx, cy) = if let Some(k) = v.get("cam_K") {
        let k = flat_numbers(k, path, "cam_K")?;
        if k.len() != 9 {
            return Err(bad(
                path,
                format!(
                    "cam_K: expected 9 numbers (3×3, row-major), found {}",
                    k.len()
                ),
            ));
        }
        check_k_shape(&k, path)?;
        (k[0], k[4], k[2], k[5])
    } else if let Some((k, _)) = v
        .as_object()
        .and_then(|o| o.iter().next())
        .filter(|(k, e)| k.parse::<u64>().is_ok() && e.get("cam_K").is_some())
    {
        return Err(bad(
            path,
            format!(
                "this looks like a BOP scene_camera.json keyed by image id ({k:?}, …): \
                 write the entry of your image to its own file (cam_K, depth_scale, width, height)"
            ),
        ));
    } else {
        let get = |key: &str| -> Result<f64> {
            let x = v.get(key).ok_or_else(|| {
                bad(path, format!("no cam_K and no {key}: expected cam_K (9 numbers, row-major) or fx, fy, cx, cy"))
            })?;
            number(x, path, key)
        };
        (get("fx")?, get("fy")?, get("cx")?, get("cy")?)
    };
    let size = match (
        size_field(v, path, "width")?,
        size_field(v, path, "height")?,
    ) {
        (Some(w), Some(h)) => Some((w, h)),
        (None, None) => None,
        _ => return Err(bad(path, "give both width and height, or neither")),
    };
    let depth_scale = match v.get("depth_scale") {
        None | Some(Value::Null) => 1.0,
        Some(x) => number(x, path, "depth_scale")?,
    };
    if depth_scale <= 0.0 {
        return Err(bad(
            path,
            format!("depth_scale must be positive, got {depth_scale}"),
        ));
    }
    let unit_mm = match v.get("unit_mm") {
        None | Some(Value::Null) => None,
        Some(x) => Some(number(x, path, "unit_mm")?),
    };
    if unit_mm.is_some_and(|u| u <= 0.0) {
        return Err(bad(path, "unit_mm must be positive"));
    }
    if !(fx > 0.0 && fy > 0.0) {
        return Err(bad(
            path,
            format!(
                "invalid intrinsics: the focal lengths must be positive (fx = {fx}, fy = {fy})"
            ),
        ));
    }
    Ok(CameraSpec {
        fx,
        fy,
        cx,
        cy,
        size,
        depth_scale,
        unit_mm,
    })
}

/// Reads a camera file. Without width/height in the file, `fallback_size` gives them (e.g. the
/// depth map's size).
pub fn read_camera(
    path: &Path,
    fallback_size: impl FnOnce() -> Result<(u32, u32)>,
) -> Result<CameraFile> {
    let v = read_json(path, "camera file")?;
    let c = parse_camera(&v, path)?;
    let (w, h) = match c.size {
        Some(s) => s,
        None => fallback_size()?,
    };
    check_intrinsics(path, &c, w, h, c.size.is_some())?;
    let intrinsics = Intrinsics::new(c.fx, c.fy, c.cx, c.cy, w, h).map_err(|e| bad(path, e))?;
    Ok(CameraFile {
        intrinsics,
        depth_scale: c.depth_scale,
        size_given: c.size.is_some(),
        unit_mm: c.unit_mm,
    })
}

/// The depth file formats read, by extension.
#[derive(Clone, Copy, PartialEq, Eq)]
enum DepthFormat {
    /// 16-bit PNG, `stored × depth_scale = mm` (BOP).
    Png,
    /// OpenEXR in metres.
    Exr,
    /// One-channel TIFF (16-bit or float), `stored × depth_scale = mm` (BOP's ITODD).
    Tiff,
}

fn depth_format(path: &Path) -> Result<DepthFormat> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "png" => Ok(DepthFormat::Png),
        "exr" => Ok(DepthFormat::Exr),
        "tif" | "tiff" => Ok(DepthFormat::Tiff),
        _ => Err(bad(
            path,
            format!(
                "unsupported depth format {ext:?}: expected a 16-bit .png (BOP, with the camera's depth_scale), a .exr in metres or a one-channel .tif (as the .png)"
            ),
        )),
    }
}

/// Whether `path` names a depth map `register` reads (by its extension: `.png`, `.exr`,
/// `.tif`, `.tiff`, any case).
pub fn is_depth_file(path: &Path) -> bool {
    depth_format(path).is_ok()
}

/// Size of a depth file from its header alone (nothing is decoded), within the readers' limits
/// ([`ic_render::io::MAX_IMAGE_SIDE`], [`ic_render::io::MAX_IMAGE_PIXELS`]).
pub fn depth_size(path: &Path) -> Result<(u32, u32)> {
    Ok(match depth_format(path)? {
        DepthFormat::Png => ic_render::io::png_size(path)?,
        DepthFormat::Exr => ic_render::io::exr_size(path)?,
        DepthFormat::Tiff => ic_render::io::tiff_size(path)?,
    })
}

/// Reads a depth map in millimetres: a 16-bit PNG or a one-channel TIFF (`stored ×
/// depth_scale = mm`), or an EXR in metres. Checks the size against the camera, and that some
/// pixel holds a valid depth.
pub fn read_depth_mm(path: &Path, camera: &CameraFile) -> Result<DepthImage> {
    let k = &camera.intrinsics;
    let expected = Some((k.width, k.height));
    let format = depth_format(path)?;
    let metres = match format {
        DepthFormat::Png => ic_render::io::read_depth_png(path, camera.depth_scale, expected)?,
        DepthFormat::Exr => ic_render::io::read_depth_exr(path, expected)?,
        DepthFormat::Tiff => ic_render::io::read_depth_tiff(path, camera.depth_scale, expected)?,
    };
    let hint = match format {
        DepthFormat::Exr => "EXR depth is read in metres",
        _ => "is the camera's depth_scale right? (stored value × depth_scale = mm)",
    };
    checked_depth_mm(metres, path, hint)
}

/// Depths in metres → a depth map in millimetres, as every depth input is checked: negative,
/// non-finite and beyond-[`MAX_DEPTH_MM`] values become missing returns (0, with a warning
/// naming `source`), and at least one pixel must hold a depth. Errors name `source` (a file
/// or an argument) and end with `hint` when every depth is beyond the limit.
pub fn checked_depth_mm(metres: Image<f32>, source: &Path, hint: &str) -> Result<DepthImage> {
    let (mut valid, mut negative, mut beyond) = (0usize, 0usize, 0usize);
    let mut farthest = 0.0f32;
    let data: Vec<f32> = metres
        .data
        .iter()
        .map(|&z| {
            let mm = z * 1000.0;
            if z.is_finite() && z > 0.0 && mm <= MAX_DEPTH_MM {
                valid += 1;
                mm
            } else {
                negative += (z.is_finite() && z < 0.0) as usize;
                if z.is_finite() && mm > MAX_DEPTH_MM {
                    beyond += 1;
                    farthest = farthest.max(z);
                }
                0.0
            }
        })
        .collect();
    if valid == 0 && beyond > 0 {
        return Err(bad(
            source,
            format!(
                "the depth map has no usable pixel: {beyond} pixels hold depths beyond {} km (up to {farthest:e} m), \
                 which no depth sensor measures, and the others are zero, negative, NaN or infinite; {hint}",
                MAX_DEPTH_MM / 1e6,
            ),
        ));
    }
    if valid == 0 {
        return Err(bad(
            source,
            "the depth map has no valid pixel (every depth is zero, negative, NaN or infinite)",
        ));
    }
    if negative > 0 {
        tracing::warn!(file = %source.display(), negative, "negative depths are treated as missing");
    }
    if beyond > 0 {
        tracing::warn!(
            file = %source.display(),
            beyond,
            farthest_m = farthest,
            "depths beyond {} km are treated as missing",
            MAX_DEPTH_MM / 1e6
        );
    }
    Ok(Image {
        width: metres.width,
        height: metres.height,
        data,
    })
}

/// Reads a mask (8-bit PNG, non-zero = object) of the camera's size; an empty mask is an error.
pub fn read_mask(path: &Path, intrinsics: &Intrinsics) -> Result<Mask> {
    let mask = ic_render::io::read_mask_png(path, Some((intrinsics.width, intrinsics.height)))?;
    if !mask.data.iter().any(|&m| m) {
        return Err(bad(path, "the mask is empty (no pixel is set)"));
    }
    Ok(mask)
}

/// Loads a mesh (OBJ, PLY, OFF, glTF/GLB) in its own units.
pub fn read_mesh(path: &Path) -> Result<Mesh> {
    Ok(ic_geometry::io::load_mesh(path)?)
}

/// Reads a pose: `{"R": 3×3 row-major, "t": [x, y, z]}`, the same nested under `"pose"` (what
/// `incontext register` writes), or BOP's `cam_R_m2c` (9 numbers) / `cam_t_m2c` (mm, converted
/// with `model_unit_mm`). Returns the pose in model units.
pub fn read_pose(path: &Path, model_unit_mm: f64) -> Result<Pose> {
    let v = read_json(path, "pose file")?;
    parse_pose(&v, path, model_unit_mm)
}

/// See [`read_pose`].
pub fn parse_pose(v: &Value, path: &Path, model_unit_mm: f64) -> Result<Pose> {
    let (r, t, scale) = if let (Some(r), Some(t)) = (v.get("R"), v.get("t")) {
        (r, t, 1.0)
    } else if let Some(p) = v.get("pose").filter(|p| p.get("R").is_some()) {
        let t = p.get("t").ok_or_else(|| bad(path, "pose: R without t"))?;
        (&p["R"], t, 1.0)
    } else if let (Some(r), Some(t)) = (v.get("cam_R_m2c"), v.get("cam_t_m2c")) {
        (r, t, 1.0 / model_unit_mm)
    } else {
        return Err(bad(
            path,
            "expected {\"R\": 3×3 row-major, \"t\": [x, y, z]} (model units) or BOP's cam_R_m2c / cam_t_m2c (mm)",
        ));
    };
    let r = flat_numbers(r, path, "R")?;
    let t = flat_numbers(t, path, "t")?;
    if r.len() != 9 || t.len() != 3 {
        return Err(bad(
            path,
            format!(
                "R must hold 9 numbers and t 3, found {} and {}",
                r.len(),
                t.len()
            ),
        ));
    }
    let rows = [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]];
    Pose::from_row_major(rows, [t[0] * scale, t[1] * scale, t[2] * scale])
        .map(|p| p.orthonormalised())
        .map_err(|e| bad(path, e))
}

/// The keys reports show first, in this order (the others follow alphabetically).
pub const REPORT_KEY_ORDER: &[&str] = &[
    "command",
    "mode",
    "seed",
    "errors",
    "pose",
    "units",
    "pose_bop",
    "truth",
    "confidence",
    "timings_ms",
    "object",
    "scene",
    "segmentation",
    "details",
    "pose_normalised",
    "inputs",
    "outputs",
    "files",
    "results",
    "failed",
    "median_seconds",
    "datasets",
    "config",
];

/// Pretty JSON with the top-level keys of an object in [`REPORT_KEY_ORDER`] (serde_json's
/// maps are sorted, which buries the pose among the details).
pub fn pretty_json(value: &Value) -> String {
    let Some(map) = value.as_object() else {
        return serde_json::to_string_pretty(value).unwrap_or_else(|_| value.to_string());
    };
    let rank = |k: &str| {
        REPORT_KEY_ORDER
            .iter()
            .position(|o| *o == k)
            .unwrap_or(REPORT_KEY_ORDER.len())
    };
    let mut keys: Vec<&String> = map.keys().collect();
    keys.sort_by(|a, b| rank(a).cmp(&rank(b)).then(a.cmp(b)));
    let mut out = String::from("{\n");
    for (i, k) in keys.iter().enumerate() {
        let v = serde_json::to_string_pretty(&map[k.as_str()]).unwrap_or_default();
        let v = v.replace('\n', "\n  ");
        let key = serde_json::to_string(k).unwrap_or_default();
        out.push_str(&format!(
            "  {key}: {v}{}\n",
            if i + 1 < keys.len() { "," } else { "" }
        ));
    }
    out.push('}');
    out
}

/// Writes `value` as pretty JSON ([`pretty_json`]), atomically.
pub fn write_json(path: &Path, value: &Value) -> Result<()> {
    let text = pretty_json(value);
    create_parent(path)?;
    ic_geometry::io::write_atomic_with(
        path,
        |w| std::io::Write::write_all(w, format!("{text}\n").as_bytes()),
        |e| e,
    )
    .map_err(|e| CliError::input(format!("{}: cannot write: {e}", path.display())))
}

/// Creates the parent folder of `path` if needed.
pub fn create_parent(path: &Path) -> Result<()> {
    ic_geometry::io::create_parent_dir(path).map_err(|e| {
        let dir = path.parent().unwrap_or(path);
        CliError::input(format!("{}: cannot create the folder: {e}", dir.display()))
    })
}

/// Creates a folder.
pub fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir)
        .map_err(|e| CliError::input(format!("{}: cannot create the folder: {e}", dir.display())))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(v: Value) -> Result<CameraSpec> {
        parse_camera(&v, Path::new("cam.json"))
    }

    #[test]
    fn cameras_read_bop_cam_k_flat_or_nested_and_fx_fy_cx_cy() {
        let flat = camera(serde_json::json!({"cam_K": [500, 0, 320, 0, 510, 240, 0, 0, 1], "depth_scale": 0.1, "width": 640, "height": 480})).unwrap();
        assert_eq!(
            (flat.fx, flat.fy, flat.cx, flat.cy),
            (500.0, 510.0, 320.0, 240.0)
        );
        assert_eq!((flat.size, flat.depth_scale), (Some((640, 480)), 0.1));
        let nested =
            camera(serde_json::json!({"cam_K": [[500, 0, 320], [0, 510, 240], [0, 0, 1]]}))
                .unwrap();
        assert_eq!(
            (nested.fx, nested.cy, nested.size, nested.depth_scale),
            (500.0, 240.0, None, 1.0)
        );
        let named = camera(serde_json::json!({"fx": 1, "fy": 2, "cx": 3, "cy": 4, "width": 8, "height": 6, "unit_mm": 100})).unwrap();
        assert_eq!(
            (named.fx, named.fy, named.cx, named.cy, named.unit_mm),
            (1.0, 2.0, 3.0, 4.0, Some(100.0))
        );
    }

    #[test]
    fn bad_cameras_name_the_file_and_the_field() {
        for (v, needle) in [
            (
                serde_json::json!({"cam_K": [0, 0, 320, 0, 510, 240, 0, 0, 1]}),
                "focal lengths must be positive",
            ),
            (
                serde_json::json!({"cam_K": [1, 2, 3]}),
                "expected 9 numbers",
            ),
            (
                serde_json::json!({"cam_K": ["a", 0, 0, 0, 1, 0, 0, 0, 1]}),
                "not a finite number",
            ),
            (serde_json::json!({"fx": 1, "fy": 1, "cx": 0}), "cy"),
            (
                serde_json::json!({"cam_K": [1, 0, 0, 0, 1, 0, 0, 0, 1], "width": 640}),
                "both width and height",
            ),
            (
                serde_json::json!({"cam_K": [1, 0, 0, 0, 1, 0, 0, 0, 1], "depth_scale": 0}),
                "depth_scale",
            ),
            (serde_json::json!([1, 2]), "JSON object"),
            (
                serde_json::json!({"0": {"cam_K": [1, 0, 0, 0, 1, 0, 0, 0, 1]}}),
                "scene_camera.json",
            ),
        ] {
            let e = camera(v).unwrap_err();
            assert_eq!(e.exit_code(), 2);
            assert!(
                e.message.starts_with("cam.json: ") && e.message.contains(needle),
                "{}",
                e.message
            );
        }
    }

    #[test]
    fn pretty_json_puts_the_pose_first_and_stays_json() {
        let v = serde_json::json!({"config": {"a": [1, 2]}, "pose": {"t": [0, 0, 1]}, "zeta": 1, "command": "x"});
        let text = pretty_json(&v);
        let back: Value = serde_json::from_str(&text).unwrap();
        assert_eq!(back, v);
        let at = |k: &str| text.find(&format!("\"{k}\"")).unwrap();
        // Listed keys in their order, the others after them.
        assert!(
            at("command") < at("pose") && at("pose") < at("config") && at("config") < at("zeta")
        );
    }

    #[test]
    fn poses_read_ours_nested_and_bop_in_mm() {
        let path = Path::new("pose.json");
        let r = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        let ours = parse_pose(&serde_json::json!({"R": r, "t": [1, 2, 3]}), path, 1.0).unwrap();
        let nested = parse_pose(
            &serde_json::json!({"pose": {"R": r, "t": [1, 2, 3]}}),
            path,
            1.0,
        )
        .unwrap();
        assert_eq!(ours, nested);
        let got = ours.rotation_row_major();
        for (a, b) in got.iter().flatten().zip(r.iter().flatten()) {
            assert!((a - b).abs() < 1e-12, "{got:?}");
        }
        // BOP: t in mm, converted to mesh units of 10 mm.
        let bop = parse_pose(
            &serde_json::json!({"cam_R_m2c": r.concat(), "cam_t_m2c": [10, 20, 30]}),
            path,
            10.0,
        )
        .unwrap();
        assert!((bop.translation - ours.translation).length() < 1e-12);
        let e = parse_pose(
            &serde_json::json!({"R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 0]}),
            path,
            1.0,
        )
        .unwrap_err();
        assert!(e.message.starts_with("pose.json: "), "{}", e.message);
        assert!(parse_pose(&serde_json::json!({"t": [0, 0, 0]}), path, 1.0).is_err());
    }
}

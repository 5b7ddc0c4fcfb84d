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

/// Reads and parses a JSON file.
pub fn read_json(path: &Path, what: &str) -> Result<Value> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| bad(path, format!("cannot read the {what}: {e}")))?;
    serde_json::from_str(&text).map_err(|e| bad(path, format!("the {what} is not valid JSON: {e}")))
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
    let intrinsics = Intrinsics::new(c.fx, c.fy, c.cx, c.cy, w, h).map_err(|e| bad(path, e))?;
    Ok(CameraFile {
        intrinsics,
        depth_scale: c.depth_scale,
        size_given: c.size.is_some(),
        unit_mm: c.unit_mm,
    })
}

/// The depth file's format, from its extension.
fn is_exr(path: &Path) -> Result<bool> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "png" => Ok(false),
        "exr" => Ok(true),
        _ => Err(bad(
            path,
            format!(
                "unsupported depth format {ext:?}: expected a 16-bit .png (BOP, with the camera's depth_scale) or a .exr in metres"
            ),
        )),
    }
}

/// Size of a depth file without decoding all of it (PNG header; EXR is decoded).
pub fn depth_size(path: &Path) -> Result<(u32, u32)> {
    if is_exr(path)? {
        let d = ic_render::io::read_depth_exr(path, None)?;
        return Ok((d.width, d.height));
    }
    let file = std::fs::File::open(path).map_err(|e| bad(path, format!("cannot read: {e}")))?;
    let reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .map_err(|e| bad(path, format!("not a readable PNG: {e}")))?;
    let info = reader.info();
    Ok((info.width, info.height))
}

/// Reads a depth map in millimetres: a 16-bit PNG (`stored × depth_scale = mm`) or an EXR in
/// metres. Checks the size against the camera, and that some pixel holds a valid depth.
pub fn read_depth_mm(path: &Path, camera: &CameraFile) -> Result<DepthImage> {
    let k = &camera.intrinsics;
    let expected = Some((k.width, k.height));
    let metres = if is_exr(path)? {
        ic_render::io::read_depth_exr(path, expected)?
    } else {
        ic_render::io::read_depth_png(path, camera.depth_scale, expected)?
    };
    let mut valid = 0usize;
    let mut negative = 0usize;
    let data: Vec<f32> = metres
        .data
        .iter()
        .map(|&z| {
            if z.is_finite() && z > 0.0 {
                valid += 1;
                z * 1000.0
            } else {
                negative += (z.is_finite() && z < 0.0) as usize;
                0.0
            }
        })
        .collect();
    if valid == 0 {
        return Err(bad(
            path,
            "the depth map has no valid pixel (every depth is zero, negative, NaN or infinite)",
        ));
    }
    if negative > 0 {
        tracing::warn!(file = %path.display(), negative, "negative depths are treated as missing");
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
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| {
            CliError::input(format!("{}: cannot create the folder: {e}", dir.display()))
        })?;
    }
    Ok(())
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

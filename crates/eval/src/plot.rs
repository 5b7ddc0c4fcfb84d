//! Accuracy-vs-threshold curves (rotation and translation), one line per method, like the
//! paper's mAP figures — as PNG and SVG. The font is embedded (DejaVu Sans Mono, see
//! `assets/DejaVu-LICENSE.txt`), so no system fonts are needed.

use std::path::Path;
use std::sync::Once;

use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

use crate::{EvalError, MethodResult, accuracy};

const FONT: &[u8] = include_bytes!("../assets/DejaVuSansMono.ttf");
pub(crate) const FONT_NAME: &str = "ic-eval-mono";

pub(crate) fn register_font() -> Result<(), EvalError> {
    static ONCE: Once = Once::new();
    let mut result = Ok(());
    ONCE.call_once(|| {
        result = plotters::style::register_font(FONT_NAME, FontStyle::Normal, FONT)
            .map_err(|_| EvalError::Plot("the embedded font could not be loaded".into()));
    });
    result
}

/// Registers the font, then calls `$draw` (a closure taking the drawing area) with a PNG or an
/// SVG drawing area of `$size` (pixels, `(u32, u32)`) for `$path`, chosen by the file's
/// extension; errors name the file. The plot is drawn in memory (an RGB buffer encoded as PNG,
/// or the SVG text) and written with `ic_geometry::io::write_atomic_with` (temporary file,
/// sync, rename), so an earlier plot is never left half-written, a failed plot leaves no
/// temporary file behind, and a link or folder in its place is refused. A macro, because the
/// two backends are different types.
macro_rules! draw_to_file {
    ($path:expr, $size:expr, $draw:expr) => {{
        let path: &std::path::Path = $path;
        let size: (u32, u32) = $size;
        crate::plot::register_font()?;
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        let bytes: Result<Vec<u8>, EvalError> = match ext.as_deref() {
            Some("png") => {
                let mut rgb = vec![0u8; size.0 as usize * size.1 as usize * 3];
                let drawn = ($draw)(BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area());
                drawn.and_then(|()| crate::plot::encode_png(&rgb, size))
            }
            Some("svg") => {
                let mut svg = String::new();
                let drawn = ($draw)(SVGBackend::with_string(&mut svg, size).into_drawing_area());
                drawn.map(|()| svg.into_bytes())
            }
            _ => Err(EvalError::Plot(
                "the plot file must end in .png or .svg".into(),
            )),
        };
        bytes
            .and_then(|bytes| crate::plot::write_plot(path, &bytes))
            .map_err(|e| match e {
                EvalError::Plot(m) => EvalError::Plot(format!("{}: {m}", path.display())),
                other => other,
            })
    }};
}
pub(crate) use draw_to_file;

/// An 8-bit RGB image of `size` (row-major, 3 bytes a pixel) as PNG bytes.
pub(crate) fn encode_png(rgb: &[u8], size: (u32, u32)) -> Result<Vec<u8>, EvalError> {
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, size.0, size.1);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()
        .and_then(|mut w| {
            w.write_image_data(rgb)?;
            w.finish()
        })
        .map_err(|e| EvalError::Plot(format!("encoding PNG: {e}")))?;
    Ok(out)
}

/// Writes a drawn plot's bytes to `path` atomically.
pub(crate) fn write_plot(path: &Path, bytes: &[u8]) -> Result<(), EvalError> {
    use std::io::Write;
    let io = |e: std::io::Error| EvalError::Plot(format!("cannot write: {e}"));
    ic_geometry::io::write_atomic_with(path, |w| w.write_all(bytes).map_err(io), io)
}

/// A chart of `x` × `y` on `area` with its axes drawn and labelled (and a caption when
/// given): the frame every plot of this module starts from.
pub(crate) fn labelled_chart<'a, DB: DrawingBackend + 'a>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    caption: Option<(&str, u32)>,
    x: std::ops::Range<f64>,
    y: std::ops::Range<f64>,
    (x_label, y_label): (&str, &str),
) -> Result<ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>, EvalError>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| EvalError::Plot(e.to_string());
    let mut builder = ChartBuilder::on(area);
    if let Some((text, size)) = caption {
        builder.caption(text, (FONT_NAME, size));
    }
    let mut chart = builder
        .margin(16)
        .x_label_area_size(44)
        .y_label_area_size(56)
        .build_cartesian_2d(x, y)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc(y_label)
        .label_style((FONT_NAME, 13))
        .axis_desc_style((FONT_NAME, 15))
        .draw()
        .map_err(err)?;
    Ok(chart)
}

/// Draws a 2-px line through `points` in `colour`, with `name` in the legend.
pub(crate) fn labelled_line<'a, DB: DrawingBackend + 'a>(
    chart: &mut ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    points: Vec<(f64, f64)>,
    colour: RGBAColor,
    name: &str,
) -> Result<(), EvalError>
where
    DB::ErrorType: 'static,
{
    chart
        .draw_series(LineSeries::new(points, colour.stroke_width(2)))
        .map_err(|e| EvalError::Plot(e.to_string()))?
        .label(name)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2)));
    Ok(())
}

/// Draws the legend of `chart` at `position` and writes `root` out.
pub(crate) fn legend_and_present<'a, DB: DrawingBackend + 'a>(
    chart: &mut ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    root: &DrawingArea<DB, plotters::coord::Shift>,
    position: SeriesLabelPosition,
) -> Result<(), EvalError>
where
    DB::ErrorType: 'static,
{
    draw_legend(chart, position)?;
    root.present().map_err(|e| EvalError::Plot(e.to_string()))
}

/// Draws the legend of `chart` at `position`.
pub(crate) fn draw_legend<'a, DB: DrawingBackend + 'a>(
    chart: &mut ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    position: SeriesLabelPosition,
) -> Result<(), EvalError>
where
    DB::ErrorType: 'static,
{
    chart
        .configure_series_labels()
        .position(position)
        .label_font((FONT_NAME, 13))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| EvalError::Plot(e.to_string()))
}

/// Which error a curve shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Curve {
    /// Rotation error, thresholds 0–max degrees.
    Rotation,
    /// Squared translation error, thresholds 0–max.
    TranslationSq,
}

/// Draws accuracy (fraction of samples with error ≤ threshold) against the threshold for
/// every method, to `path` (the extension picks PNG or SVG).
pub fn plot_accuracy_curves(
    path: &Path,
    results: &[MethodResult],
    curve: Curve,
    max: f64,
) -> Result<(), EvalError> {
    plot_accuracy_curves_titled(path, results, curve, max, None)
}

/// [`plot_accuracy_curves`] with a title of its own (default: "Rotation accuracy" or
/// "Translation accuracy").
pub fn plot_accuracy_curves_titled(
    path: &Path,
    results: &[MethodResult],
    curve: Curve,
    max: f64,
    title: Option<&str>,
) -> Result<(), EvalError> {
    draw_to_file!(path, (720, 480), |root| draw(
        root, results, curve, max, title
    ))
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, plotters::coord::Shift>,
    results: &[MethodResult],
    curve: Curve,
    max: f64,
    title: Option<&str>,
) -> Result<(), EvalError>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| EvalError::Plot(e.to_string());
    root.fill(&WHITE).map_err(err)?;
    let (title_default, x_label) = match curve {
        Curve::Rotation => ("Rotation accuracy", "rotation error threshold (degrees)"),
        Curve::TranslationSq => (
            "Translation accuracy",
            "squared translation error threshold",
        ),
    };
    let title = title.unwrap_or(title_default);
    let mut chart = labelled_chart(
        &root,
        Some((title, 22)),
        0.0..max,
        0.0..1.0,
        (x_label, "accuracy"),
    )?;
    let steps = 200;
    for (i, r) in results.iter().enumerate() {
        let errors = match curve {
            Curve::Rotation => &r.rotation_errors_deg,
            Curve::TranslationSq => &r.translation_sq_errors,
        };
        let colour = Palette99::pick(i).to_rgba();
        let points: Vec<(f64, f64)> = (0..=steps)
            .map(|k| {
                let t = max * k as f64 / steps as f64;
                (t, accuracy(errors, t))
            })
            .collect();
        labelled_line(&mut chart, points, colour, &r.method)?;
    }
    legend_and_present(&mut chart, &root, SeriesLabelPosition::LowerRight)
}

/// Draws lines through `(x, y)` points, one per series with its markers, to `path` (.png or
/// .svg): e.g. accuracy against the number of hypotheses. The y axis spans [0, `y_max`].
pub fn plot_xy(
    path: &Path,
    title: &str,
    (x_label, y_label): (&str, &str),
    y_max: f64,
    series: &[(String, Vec<(f64, f64)>)],
) -> Result<(), EvalError> {
    let labels = (x_label, y_label);
    draw_to_file!(path, (720, 480), |root| draw_xy(
        root, title, labels, y_max, series
    ))
}

fn draw_xy<DB: DrawingBackend>(
    root: DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    (x_label, y_label): (&str, &str),
    y_max: f64,
    series: &[(String, Vec<(f64, f64)>)],
) -> Result<(), EvalError>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| EvalError::Plot(e.to_string());
    root.fill(&WHITE).map_err(err)?;
    let xs = series.iter().flat_map(|s| s.1.iter().map(|p| p.0));
    let x_max = xs.fold(1.0f64, f64::max) * 1.05;
    let mut chart = labelled_chart(
        &root,
        Some((title, 20)),
        0.0..x_max,
        0.0..y_max,
        (x_label, y_label),
    )?;
    for (i, (name, points)) in series.iter().enumerate() {
        let colour = Palette99::pick(i).to_rgba();
        labelled_line(&mut chart, points.clone(), colour, name)?;
        chart
            .draw_series(points.iter().map(|&p| Circle::new(p, 4, colour.filled())))
            .map_err(err)?;
    }
    legend_and_present(&mut chart, &root, SeriesLabelPosition::LowerRight)
}

/// Learning curves of training runs, two panels over a shared x axis (e.g. iterations):
/// `top` (e.g. the training loss, its y range fitted to the data) above `bottom` (e.g. a
/// validation metric; its y range is [0, 1] when every value lies there, else fitted), one
/// line per run in the same colour in both panels, to `path` (.png or .svg).
pub fn plot_learning_curves(
    path: &Path,
    title: &str,
    (x_label, top_label, bottom_label): (&str, &str, &str),
    top: &[(String, Vec<(f64, f64)>)],
    bottom: &[(String, Vec<(f64, f64)>)],
) -> Result<(), EvalError> {
    let labels = (x_label, top_label, bottom_label);
    draw_to_file!(path, (820, 720), |root| draw_learning(
        root, title, labels, top, bottom
    ))
}

/// The x range shared by both panels and a padded y range of `series` (`unit`: [0, 1] when
/// every value lies in it). The y range leaves out the first 2 % of the x axis, where a loss
/// from scratch starts an order of magnitude above where it spends the run.
fn ranges(
    series: &[(String, Vec<(f64, f64)>)],
    unit: bool,
) -> (std::ops::Range<f64>, std::ops::Range<f64>) {
    let points = || series.iter().flat_map(|s| s.1.iter().copied());
    let x_max = points().map(|p| p.0).fold(1.0f64, f64::max);
    let skip = if points().any(|p| p.0 >= 0.02 * x_max) {
        0.02 * x_max
    } else {
        f64::NEG_INFINITY
    };
    let (lo, hi) = points()
        .filter(|p| p.0 >= skip)
        .map(|p| p.1)
        .filter(|y| y.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), y| {
            (a.min(y), b.max(y))
        });
    let y = if !lo.is_finite() || (unit && lo >= 0.0 && hi <= 1.0) {
        0.0..1.0
    } else {
        let pad = ((hi - lo) * 0.05).max(1e-6);
        (lo - pad)..(hi + pad)
    };
    (0.0..x_max * 1.02, y)
}

fn draw_learning<DB: DrawingBackend>(
    root: DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    (x_label, top_label, bottom_label): (&str, &str, &str),
    top: &[(String, Vec<(f64, f64)>)],
    bottom: &[(String, Vec<(f64, f64)>)],
) -> Result<(), EvalError>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| EvalError::Plot(e.to_string());
    root.fill(&WHITE).map_err(err)?;
    let root = root.titled(title, (FONT_NAME, 20)).map_err(err)?;
    let (upper, lower) = root.split_vertically(root.dim_in_pixel().1 / 2);
    let (x_top, y_top) = ranges(top, false);
    let (x_bottom, y_bottom) = ranges(bottom, true);
    let x = 0.0..x_top.end.max(x_bottom.end);
    for (area, series, y_label, y) in [
        (&upper, top, top_label, y_top),
        (&lower, bottom, bottom_label, y_bottom),
    ] {
        let mut chart = labelled_chart(area, None, x.clone(), y, (x_label, y_label))?;
        for (i, (name, points)) in series.iter().enumerate() {
            let colour = Palette99::pick(i).to_rgba();
            labelled_line(&mut chart, points.clone(), colour, name)?;
        }
        draw_legend(&mut chart, SeriesLabelPosition::UpperRight)?;
    }
    root.present().map_err(err)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Summary;

    fn result(name: &str, scale: f64) -> MethodResult {
        let rot: Vec<f64> = (0..100).map(|i| i as f64 * scale).collect();
        let tsq: Vec<f64> = (0..100).map(|i| i as f64 * scale * 1e-4).collect();
        MethodResult {
            method: name.into(),
            summary: Summary::new(&[], None),
            rotation_errors_deg: rot,
            translation_sq_errors: tsq,
            seconds_median: None,
        }
    }

    #[test]
    fn writes_png_and_svg_with_one_line_per_method() {
        let dir = tempfile::tempdir().unwrap();
        let results = [result("ours-ot", 0.2), result("icp", 0.5)];
        let png = dir.path().join("rot.png");
        plot_accuracy_curves(&png, &results, Curve::Rotation, 30.0).unwrap();
        let bytes = std::fs::read(&png).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
        let svg = dir.path().join("trans.svg");
        plot_accuracy_curves(&svg, &results, Curve::TranslationSq, 1e-2).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(
            text.contains("ours-ot")
                && text.contains("icp")
                && text.contains("Translation accuracy")
        );
        // The two curves and their two legend marks are the only 2-px strokes.
        assert_eq!(text.matches(r#"stroke-width="2""#).count(), 4, "{text}");
        let xy = dir.path().join("xy.svg");
        plot_xy(
            &xy,
            "accuracy against K",
            ("K", "accuracy"),
            1.0,
            &[("set".into(), vec![(1.0, 0.2), (24.0, 0.8)])],
        )
        .unwrap();
        assert!(
            std::fs::read_to_string(&xy)
                .unwrap()
                .contains("accuracy against K")
        );
        let curves = dir.path().join("curves.svg");
        plot_learning_curves(
            &curves,
            "two runs",
            ("iteration", "loss", "acc@15°"),
            &[
                ("scratch".into(), vec![(1.0, 9.0), (500.0, 3.5)]),
                ("fine-tune".into(), vec![(1.0, 3.6), (500.0, 3.2)]),
            ],
            &[
                ("scratch".into(), vec![(250.0, 0.1), (500.0, 0.3)]),
                ("fine-tune".into(), vec![(250.0, 0.6), (500.0, 0.62)]),
            ],
        )
        .unwrap();
        let text = std::fs::read_to_string(&curves).unwrap();
        // Two panels, each with both runs and their two legend marks.
        assert_eq!(text.matches(r#"stroke-width="2""#).count(), 8, "{text}");
        assert!(text.contains("two runs") && text.contains("fine-tune"));
        if let Ok(keep) = std::env::var("IC_EVAL_KEEP_PLOT") {
            plot_accuracy_curves(Path::new(&keep), &results, Curve::Rotation, 30.0).unwrap();
        }
        assert!(
            plot_accuracy_curves(&dir.path().join("x.gif"), &results, Curve::Rotation, 30.0)
                .is_err()
        );
    }

    #[test]
    fn a_plot_is_renamed_into_place_and_a_failed_one_leaves_no_partial_file() {
        let dir = tempfile::tempdir().unwrap();
        let results = [result("ours-ot", 0.2)];
        let svg = dir.path().join("rot.svg");
        std::fs::write(&svg, "earlier").unwrap();
        plot_accuracy_curves(&svg, &results, Curve::Rotation, 30.0).unwrap();
        assert!(std::fs::read_to_string(&svg).unwrap().contains("ours-ot"));
        // A PNG is drawn in memory and encoded at the plot's size, not blank.
        let png_path = dir.path().join("rot.png");
        plot_accuracy_curves(&png_path, &results, Curve::Rotation, 30.0).unwrap();
        let decoder = png::Decoder::new(std::io::BufReader::new(
            std::fs::File::open(&png_path).unwrap(),
        ));
        let mut reader = decoder.read_info().unwrap();
        let mut pixels = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut pixels).unwrap();
        assert_eq!((info.width, info.height), (720, 480));
        assert!(pixels.iter().any(|&p| p < 128) && pixels.iter().any(|&p| p > 128));
        // A folder where the plot should go: drawing succeeds, the write is refused.
        let taken = dir.path().join("taken.png");
        std::fs::create_dir(&taken).unwrap();
        let err = plot_accuracy_curves(&taken, &results, Curve::Rotation, 30.0).unwrap_err();
        assert!(err.to_string().contains("taken.png"), "{err}");
        assert!(taken.is_dir());
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, ["rot.png", "rot.svg", "taken.png"]);
    }
}

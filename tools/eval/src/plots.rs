//! The figures of a flight report, as PNG files: trajectory, errors against
//! time and height, inliers/outliers per frame, inlier residual histogram.
//!
//! Text is drawn with ab_glyph from a TTF file registered at runtime
//! ([`FONT_PATH`]), so no fontconfig/freetype is needed.

use std::error::Error;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use image::ImageEncoder;
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};
use trn_flight::{FixStatus, Flight, TimedPose};
use trn_geodesy::LocalFrame;

use crate::metrics::{stats, FrameEval};
use crate::{EvalError, RunReport};

/// The font the figures' text is drawn with (Debian package `fonts-dejavu-core`).
pub const FONT_PATH: &str = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf";
pub const FONT_PACKAGE: &str = "fonts-dejavu-core";

pub const TRAJECTORY_PNG: &str = "trajectory.png";
pub const ERROR_TIME_PNG: &str = "error_time.png";
pub const ERROR_HEIGHT_PNG: &str = "error_height.png";
pub const INLIERS_PNG: &str = "inliers.png";
pub const RESIDUALS_PNG: &str = "residuals.png";

/// Pixel size of each figure.
pub const TRAJECTORY_SIZE: (u32, u32) = (1200, 1050);
pub const ERROR_TIME_SIZE: (u32, u32) = (1200, 850);
pub const ERROR_HEIGHT_SIZE: (u32, u32) = (900, 900);
pub const INLIERS_SIZE: (u32, u32) = (1200, 600);
pub const RESIDUALS_SIZE: (u32, u32) = (1000, 650);

const FIX: RGBColor = RGBColor(44, 160, 44);
const PROPAGATED: RGBColor = RGBColor(255, 127, 14);
const LOST: RGBColor = RGBColor(214, 39, 40);
const EAST: RGBColor = RGBColor(31, 119, 180);
const NORTH: RGBColor = RGBColor(148, 103, 189);
const UP: RGBColor = RGBColor(140, 86, 75);

type PlotResult = Result<(), Box<dyn Error>>;
type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;

/// Registers [`FONT_PATH`] with plotters (once per process).
pub fn ensure_font() -> Result<(), EvalError> {
    static FONT: OnceLock<Result<(), String>> = OnceLock::new();
    FONT.get_or_init(|| {
        let bytes = read_font(Path::new(FONT_PATH))?;
        // plotters keeps a 'static reference; the font lives for the process anyway.
        let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        register_font("sans-serif", FontStyle::Normal, bytes)
            .map_err(|_| format!("font {FONT_PATH}: not a TrueType/OpenType font"))
    })
    .clone()
    .map_err(EvalError::Font)
}

fn read_font(path: &Path) -> Result<Vec<u8>, String> {
    std::fs::read(path).map_err(|e| {
        format!("font {}: {e} (the plots need it: install the Debian package {FONT_PACKAGE})", path.display())
    })
}

/// Writes the five figures of one run into `dir` (created if missing); the
/// residual histogram only when the run has a `matches.csv`. Returns the
/// files written.
pub fn plot_run(dir: &Path, flight: &Flight, run: &RunReport) -> Result<Vec<PathBuf>, EvalError> {
    ensure_font()?;
    std::fs::create_dir_all(dir)
        .map_err(|e| EvalError::Output { path: dir.to_path_buf(), reason: e.to_string() })?;
    let mut written = Vec::new();
    let mut out =
        |name: &str, size: (u32, u32), draw: &dyn Fn(&Area) -> PlotResult| -> Result<(), EvalError> {
            let path = dir.join(name);
            render_png(&path, size, draw)?;
            written.push(path);
            Ok(())
        };
    out(TRAJECTORY_PNG, TRAJECTORY_SIZE, &|a| trajectory(a, flight, run))?;
    out(ERROR_TIME_PNG, ERROR_TIME_SIZE, &|a| error_time(a, run))?;
    out(ERROR_HEIGHT_PNG, ERROR_HEIGHT_SIZE, &|a| error_height(a, run))?;
    out(INLIERS_PNG, INLIERS_SIZE, &|a| inliers(a, run))?;
    match &run.matches {
        Some(_) => out(RESIDUALS_PNG, RESIDUALS_SIZE, &|a| residuals(a, run))?,
        None => tracing::info!("{}: no matches.csv, skipping {RESIDUALS_PNG}", run.label),
    }
    for p in &written {
        tracing::info!("wrote {}", p.display());
    }
    Ok(written)
}

/// Draws into an RGB buffer, then writes the PNG under a temporary name and
/// renames it.
fn render_png(path: &Path, (w, h): (u32, u32), draw: &dyn Fn(&Area) -> PlotResult) -> Result<(), EvalError> {
    let fail =
        |e: &dyn std::fmt::Display| EvalError::Output { path: path.to_path_buf(), reason: e.to_string() };
    let mut buf = vec![255u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| fail(&e))?;
        draw(&root).map_err(|e| fail(&e))?;
        root.present().map_err(|e| fail(&e))?;
    }
    trn_flight::write_atomic(path, |out| {
        image::codecs::png::PngEncoder::new(out)
            .write_image(&buf, w, h, image::ExtendedColorType::Rgb8)
            .map_err(std::io::Error::other)
    })?;
    Ok(())
}

/// `lo..hi` padded by 5%, never empty.
fn padded(values: impl IntoIterator<Item = f64>) -> Range<f64> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.into_iter().filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if lo > hi {
        return 0.0..1.0;
    }
    let pad = ((hi - lo) * 0.05).max(1e-3 * hi.abs().max(lo.abs())).max(1e-3);
    lo - pad..hi + pad
}

/// `0..max` padded.
fn from_zero(values: impl IntoIterator<Item = f64>) -> Range<f64> {
    let r = padded(values.into_iter().chain([0.0]));
    0.0..r.end
}

fn time_range(run: &RunReport) -> Range<f64> {
    padded(run.per_frame.iter().map(|f| f.t))
}

type Chart<'a, 'b> = ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// Decimals for tick labels: about ten ticks over `r`.
fn decimals(r: &Range<f64>) -> usize {
    let step = (r.end - r.start) / 10.0;
    if step >= 1.0 || step <= 0.0 {
        0
    } else {
        ((-step.log10()).ceil() as usize).min(6)
    }
}

fn draw_mesh(chart: &mut Chart, x_desc: &str, y_desc: &str, x_mesh: bool) -> PlotResult {
    let (xd, yd) = (decimals(&chart.x_range()), decimals(&chart.y_range()));
    let xf = move |v: &f64| format!("{v:.xd$}");
    let yf = move |v: &f64| format!("{v:.yd$}");
    let mut mesh = chart.configure_mesh();
    mesh.x_desc(x_desc)
        .y_desc(y_desc)
        .x_label_formatter(&xf)
        .y_label_formatter(&yf)
        .label_style(("sans-serif", 15))
        .axis_desc_style(("sans-serif", 17));
    if !x_mesh {
        mesh.disable_x_mesh();
    }
    mesh.draw()?;
    Ok(())
}

fn status_color(s: FixStatus) -> RGBColor {
    match s {
        FixStatus::Fix => FIX,
        FixStatus::Propagated => PROPAGATED,
        FixStatus::Lost => LOST,
    }
}

fn legend_line(c: RGBColor) -> impl Fn((i32, i32)) -> PathElement<(i32, i32)> {
    move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
}

fn legend_dot(c: RGBColor) -> impl Fn((i32, i32)) -> Circle<(i32, i32), i32> {
    move |(x, y)| Circle::new((x + 10, y), 4, c.filled())
}

fn legend_cross(c: RGBColor) -> impl Fn((i32, i32)) -> Cross<(i32, i32), i32> {
    move |(x, y)| Cross::new((x + 10, y), 4, c.stroke_width(2))
}

fn poses_with(run: &RunReport, s: FixStatus) -> impl Iterator<Item = &FrameEval> {
    run.per_frame.iter().filter(move |f| f.status == s && f.estimate.is_some())
}

/// East, north, up (m) of a pose relative to the first frame's truth.
fn enu_of(origin: &LocalFrame, p: &TimedPose) -> [f64; 3] {
    let e = origin.to_enu(&p.position.to_ecef()).0;
    [e.x, e.y, e.z]
}

fn trajectory(root: &Area, flight: &Flight, run: &RunReport) -> PlotResult {
    let root = root.titled(&format!("Trajectory, estimate vs truth: {}", run.label), ("sans-serif", 26))?;
    let first = &run.per_frame[0];
    let origin = LocalFrame::at(first.truth.position);
    let tr = time_range(run);
    let truth: Vec<(f64, [f64; 3])> = flight
        .truth
        .iter()
        .flatten()
        .filter(|p| tr.contains(&p.t))
        .map(|p| (p.t, enu_of(&origin, p)))
        .collect();
    let est = |s: FixStatus| -> Vec<(f64, [f64; 3])> {
        poses_with(run, s).map(|f| (f.t, enu_of(&origin, f.estimate.as_ref().unwrap()))).collect()
    };
    let (fix, prop) = (est(FixStatus::Fix), est(FixStatus::Propagated));
    let lost: Vec<(f64, [f64; 3])> = run
        .per_frame
        .iter()
        .filter(|f| f.status == FixStatus::Lost)
        .map(|f| (f.t, enu_of(&origin, &f.truth)))
        .collect();
    let names = ["east (m)", "north (m)", "up (m)"];
    for (k, panel) in root.split_evenly((3, 1)).iter().enumerate() {
        let yr = padded(truth.iter().chain(&fix).chain(&prop).map(|(_, e)| e[k]));
        let mut chart = ChartBuilder::on(panel)
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(95)
            .build_cartesian_2d(tr.clone(), yr)?;
        draw_mesh(&mut chart, "time (s)", names[k], true)?;
        chart
            .draw_series(LineSeries::new(truth.iter().map(|(t, e)| (*t, e[k])), BLACK.stroke_width(2)))?
            .label("truth")
            .legend(legend_line(BLACK));
        chart
            .draw_series(fix.iter().map(|(t, e)| Circle::new((*t, e[k]), 3, FIX.filled())))?
            .label("estimate: fix")
            .legend(legend_dot(FIX));
        chart
            .draw_series(prop.iter().map(|(t, e)| Circle::new((*t, e[k]), 3, PROPAGATED.filled())))?
            .label("estimate: propagated")
            .legend(legend_dot(PROPAGATED));
        chart
            .draw_series(lost.iter().map(|(t, e)| Cross::new((*t, e[k]), 5, LOST.stroke_width(2))))?
            .label("lost (at truth)")
            .legend(legend_cross(LOST));
        if k == 0 {
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperLeft)
                .label_font(("sans-serif", 15))
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .draw()?;
        }
    }
    Ok(())
}

fn error_time(root: &Area, run: &RunReport) -> PlotResult {
    let root = root.titled(&format!("Position error vs time: {}", run.label), ("sans-serif", 26))?;
    let panels = root.split_evenly((2, 1));
    let tr = time_range(run);
    let with_pose: Vec<&FrameEval> = run.per_frame.iter().filter(|f| f.error.is_some()).collect();
    let err = |f: &FrameEval| f.error.unwrap();

    let mut chart = ChartBuilder::on(&panels[0])
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(95)
        .build_cartesian_2d(tr.clone(), from_zero(with_pose.iter().map(|f| err(f).pos_m)))?;
    draw_mesh(&mut chart, "time (s)", "3D position error (m)", true)?;
    chart.draw_series(LineSeries::new(with_pose.iter().map(|f| (f.t, err(f).pos_m)), BLACK.mix(0.4)))?;
    for s in [FixStatus::Fix, FixStatus::Propagated] {
        let c = status_color(s);
        chart
            .draw_series(
                with_pose
                    .iter()
                    .filter(|f| f.status == s)
                    .map(|f| Circle::new((f.t, err(f).pos_m), 3, c.filled())),
            )?
            .label(s.as_str())
            .legend(legend_dot(c));
    }
    chart
        .draw_series(
            run.per_frame
                .iter()
                .filter(|f| f.status == FixStatus::Lost)
                .map(|f| Cross::new((f.t, 0.0), 5, LOST.stroke_width(2))),
        )?
        .label("lost")
        .legend(legend_cross(LOST));
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .label_font(("sans-serif", 15))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;

    let yr = padded(with_pose.iter().flat_map(|f| err(f).enu_m).chain([0.0]));
    let mut chart = ChartBuilder::on(&panels[1])
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(95)
        .build_cartesian_2d(tr, yr)?;
    draw_mesh(&mut chart, "time (s)", "error, estimate - truth (m)", true)?;
    for (k, (name, c)) in [("east", EAST), ("north", NORTH), ("up", UP)].into_iter().enumerate() {
        chart
            .draw_series(LineSeries::new(
                with_pose.iter().map(|f| (f.t, err(f).enu_m[k])),
                c.stroke_width(2),
            ))?
            .label(name)
            .legend(legend_line(c));
        chart.draw_series(with_pose.iter().map(|f| Circle::new((f.t, err(f).enu_m[k]), 2, c.filled())))?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .label_font(("sans-serif", 15))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

fn error_height(root: &Area, run: &RunReport) -> PlotResult {
    let root = root.titled(&format!("Position error vs height: {}", run.label), ("sans-serif", 26))?;
    let with_pose: Vec<&FrameEval> = run.per_frame.iter().filter(|f| f.error.is_some()).collect();
    let xr = from_zero(with_pose.iter().map(|f| f.error.unwrap().pos_m));
    let yr = padded(run.per_frame.iter().map(|f| f.truth_h_m / 1000.0));
    let mut chart = ChartBuilder::on(&root)
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(80)
        .build_cartesian_2d(xr, yr)?;
    draw_mesh(&mut chart, "3D position error (m)", "true height above ellipsoid (km)", true)?;
    for s in [FixStatus::Fix, FixStatus::Propagated] {
        let c = status_color(s);
        chart
            .draw_series(
                with_pose
                    .iter()
                    .filter(|f| f.status == s)
                    .map(|f| Circle::new((f.error.unwrap().pos_m, f.truth_h_m / 1000.0), 3, c.filled())),
            )?
            .label(s.as_str())
            .legend(legend_dot(c));
    }
    chart
        .draw_series(
            run.per_frame
                .iter()
                .filter(|f| f.status == FixStatus::Lost)
                .map(|f| Cross::new((0.0, f.truth_h_m / 1000.0), 5, LOST.stroke_width(2))),
        )?
        .label("lost")
        .legend(legend_cross(LOST));
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .label_font(("sans-serif", 15))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

fn inliers(root: &Area, run: &RunReport) -> PlotResult {
    let root =
        root.titled(&format!("RANSAC inliers and outliers per frame: {}", run.label), ("sans-serif", 26))?;
    let rows: Vec<(f64, f64, f64)> = run
        .per_frame
        .iter()
        .filter_map(|f| {
            let (i, m) = (f.inliers? as f64, f.matches? as f64);
            Some((f.t, i, (m - i).max(0.0)))
        })
        .collect();
    let yr = from_zero(rows.iter().flat_map(|r| [r.1, r.2]));
    // Room for the legend above the curves.
    let yr = 0.0..yr.end * 1.2;
    let mut chart = ChartBuilder::on(&root)
        .margin(10)
        .x_label_area_size(45)
        .y_label_area_size(80)
        .build_cartesian_2d(time_range(run), yr)?;
    draw_mesh(&mut chart, "time (s)", "matches per frame", true)?;
    for (name, c, pick) in [("inliers", FIX, 1usize), ("outliers (matches - inliers)", LOST, 2)] {
        let v = |r: &(f64, f64, f64)| (r.0, if pick == 1 { r.1 } else { r.2 });
        chart
            .draw_series(LineSeries::new(rows.iter().map(v), c.stroke_width(2)))?
            .label(name)
            .legend(legend_line(c));
        chart.draw_series(rows.iter().map(|r| Circle::new(v(r), 2, c.filled())))?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .label_font(("sans-serif", 15))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

fn residuals(root: &Area, run: &RunReport) -> PlotResult {
    let r = &run.inlier_residuals_px;
    let caption = match stats(r) {
        Some(s) => format!(
            "Inlier reprojection error: {} (n={}, median {:.2} px, p95 {:.2} px)",
            run.label, s.n, s.median, s.p95
        ),
        None => format!("Inlier reprojection error: {} (no inliers)", run.label),
    };
    let root = root.titled(&caption, ("sans-serif", 24))?;
    const BINS: usize = 40;
    let hi = r.iter().copied().fold(0.0f64, f64::max).max(1e-3) * 1.0001;
    let w = hi / BINS as f64;
    let mut counts = [0usize; BINS];
    for v in r {
        counts[((v / w) as usize).min(BINS - 1)] += 1;
    }
    let top = counts.iter().copied().max().unwrap_or(0).max(1) as f64 * 1.08;
    let mut chart = ChartBuilder::on(&root)
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(80)
        .build_cartesian_2d(0.0..hi, 0.0..top)?;
    draw_mesh(&mut chart, "reprojection error under the final pose (px)", "inlier matches", false)?;
    chart.draw_series(counts.iter().enumerate().map(|(i, &c)| {
        Rectangle::new([(i as f64 * w, 0.0), ((i + 1) as f64 * w, c as f64)], EAST.mix(0.75).filled())
    }))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_font_names_the_file_and_the_package() {
        let e = read_font(Path::new("/nonexistent/DejaVuSans.ttf")).unwrap_err();
        assert!(e.contains("/nonexistent/DejaVuSans.ttf") && e.contains(FONT_PACKAGE), "{e}");
    }

    #[test]
    fn tick_decimals_follow_the_range() {
        assert_eq!(decimals(&(0.0..14000.0)), 0);
        assert_eq!(decimals(&(0.0..1.0)), 1);
        assert_eq!(decimals(&(0.0..0.09)), 3);
        assert_eq!(decimals(&(5.0..5.0)), 0);
    }

    #[test]
    fn padded_ranges_are_never_empty() {
        let r = padded([3.0, 3.0]);
        assert!(r.start < 3.0 && r.end > 3.0);
        assert_eq!(padded(std::iter::empty()), 0.0..1.0);
        assert_eq!(from_zero([2.0, 10.0]).start, 0.0);
    }
}

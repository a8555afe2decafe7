//! Scores a navigator's output against a flight's true trajectory: what
//! `trn evaluate` does.
//!
//! For every frame of the flight's `frames.csv`, the navigator's `poses.csv`
//! row at that time (within [`metrics::TIME_TOL_S`]) is compared with
//! `truth.csv`: 3D position error (ECEF distance), its east/north/up
//! components in the truth's local frame, attitude and boresight pointing
//! errors. A frame without a row counts as lost. [`evaluate`] gathers these
//! into a [`RunReport`] per run (statistics over `fix` frames and over all
//! frames with a pose, shares by status, truth-height bands, timing), and
//! with several runs (e.g. the same flight at 2 and 4 Hz, with and without
//! gyro propagation) a [`metrics::Comparison`] of the share of each run's
//! rows with status `fix` per altitude segment. [`Evaluation`] serializes to
//! JSON and prints as tables (`Display`); [`plots`] draws the figures.
//!
//! ```
//! use nalgebra::UnitQuaternion;
//! use trn_eval::metrics::pose_error;
//! use trn_flight::TimedPose;
//! use trn_geodesy::Geodetic;
//!
//! // A fix 30 m above the truth, its attitude 1 deg off about the vertical axis.
//! let truth = TimedPose { t: 0.0, position: Geodetic::new(40.0, -111.0, 30_000.0), q_ecef_cam: UnitQuaternion::identity() };
//! let est = TimedPose {
//!     position: Geodetic::new(40.0, -111.0, 30_030.0),
//!     q_ecef_cam: UnitQuaternion::from_euler_angles(0.0, 0.0, 1f64.to_radians()),
//!     ..truth
//! };
//! let e = pose_error(&truth, &est);
//! assert!((e.pos_m - 30.0).abs() < 1e-6 && (e.enu_m[2] - 30.0).abs() < 1e-6);
//! assert!((e.att_deg - 1.0).abs() < 1e-9);
//! ```

use std::collections::HashSet;
use std::fmt;
use std::path::{Path, PathBuf};

use serde::Serialize;
use trn_flight::{Flight, FlightError};

pub mod metrics;
pub mod plots;

use metrics::{Band, Comparison, ErrorStats, FrameEval, Stats, StatusCounts};

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(transparent)]
    Flight(#[from] FlightError),
    #[error("{0}")]
    Input(String),
    #[error("{}: {reason}", path.display())]
    Output { path: PathBuf, reason: String },
    #[error("{0}")]
    Font(String),
}

/// One navigator run to score.
#[derive(Clone, Debug)]
pub struct RunInput {
    /// Names the run in tables and its plot subfolder.
    pub label: String,
    pub poses: PathBuf,
    /// Per-match residuals; `None`: `matches.csv` next to `poses` if it exists.
    pub matches: Option<PathBuf>,
}

impl RunInput {
    /// Labelled by the poses file's stem.
    pub fn new(poses: PathBuf) -> Self {
        let label =
            poses.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "run".into());
        Self { label, poses, matches: None }
    }
}

#[derive(Clone, Debug)]
pub struct Options {
    /// Height of the altitude bands (m).
    pub band_m: f64,
    /// Where to write the figures (one subfolder per run when several).
    pub plot_dir: Option<PathBuf>,
}

impl Default for Options {
    fn default() -> Self {
        Self { band_m: 5000.0, plot_dir: None }
    }
}

/// The score of one run.
#[derive(Clone, Debug, Serialize)]
pub struct RunReport {
    pub label: String,
    pub poses: PathBuf,
    /// The `matches.csv` read, if any.
    pub matches: Option<PathBuf>,
    /// Rows in `poses.csv`.
    pub rows: usize,
    /// Rows at no frame's time (not scored).
    pub rows_ignored: usize,
    /// Over all flight frames; frames without a row count as lost.
    pub status: StatusCounts,
    /// Errors over `fix` frames.
    pub fix_errors: Option<ErrorStats>,
    /// Errors over frames with a pose (`fix` and `propagated`).
    pub pose_errors: Option<ErrorStats>,
    /// Truth-height bands, highest first.
    pub bands: Vec<Band>,
    /// `ms` over the scored rows.
    pub timing_ms: Option<Stats>,
    /// Reprojection error of inlier matches (px), from `matches.csv`.
    pub inlier_residual_px: Option<Stats>,
    /// The `covariance.csv` next to `poses`, if any, and how well its
    /// position covariances fit the fixes' errors (NEES).
    pub covariance: Option<PathBuf>,
    pub consistency: Option<metrics::Consistency>,
    pub per_frame: Vec<FrameEval>,
    #[serde(skip)]
    pub inlier_residuals_px: Vec<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Evaluation {
    pub flight: PathBuf,
    pub frames: usize,
    pub band_m: f64,
    /// How `p95` is computed.
    pub percentile: &'static str,
    pub runs: Vec<RunReport>,
    /// With two runs or more.
    pub comparison: Option<Comparison>,
    /// Figures written.
    pub plots: Vec<PathBuf>,
}

/// Scores each run against the flight's truth, and draws the figures when
/// `opts.plot_dir` is set.
pub fn evaluate(flight_dir: &Path, runs: &[RunInput], opts: &Options) -> Result<Evaluation, EvalError> {
    if runs.is_empty() {
        return Err(EvalError::Input("no poses file to evaluate".into()));
    }
    if !(opts.band_m.is_finite() && opts.band_m > 0.0) {
        return Err(EvalError::Input(format!("band height {} m must be positive", opts.band_m)));
    }
    let mut seen = HashSet::new();
    for r in runs {
        if r.label.is_empty() || r.label.contains(['/', '\\']) || r.label == "." || r.label == ".." {
            return Err(EvalError::Input(format!("label {:?} cannot name a plot folder", r.label)));
        }
        if !seen.insert(r.label.as_str()) {
            return Err(EvalError::Input(format!("label {:?} is given to two runs", r.label)));
        }
    }
    let flight = Flight::open(flight_dir)?;
    let truth_path = flight_dir.join(trn_flight::TRUTH_FILE);
    if flight.truth.is_none() {
        return Err(FlightError::new(
            &truth_path,
            None,
            "no such file: evaluation needs the true trajectory",
        )
        .into());
    }
    let truths = flight
        .frames
        .iter()
        .map(|f| {
            flight.truth_at(f.t).ok_or_else(|| {
                FlightError::new(
                    &truth_path,
                    None,
                    format!("no true pose at frame time {} (outside its time span)", f.t),
                )
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    tracing::info!("flight {}: {} frames", flight_dir.display(), truths.len());

    let mut reports = Vec::with_capacity(runs.len());
    for r in runs {
        reports.push(score_run(&truths, r, opts.band_m)?);
    }
    let comparison = (reports.len() > 1).then(|| {
        let rs: Vec<(&str, &[FrameEval])> =
            reports.iter().map(|r| (r.label.as_str(), &r.per_frame[..])).collect();
        metrics::compare(&rs, opts.band_m)
    });
    let mut plots = Vec::new();
    if let Some(dir) = &opts.plot_dir {
        for r in &reports {
            let d = if reports.len() > 1 { dir.join(&r.label) } else { dir.clone() };
            plots.extend(plots::plot_run(&d, &flight, r)?);
        }
    }
    Ok(Evaluation {
        flight: flight_dir.to_path_buf(),
        frames: truths.len(),
        band_m: opts.band_m,
        percentile: "nearest-rank",
        runs: reports,
        comparison,
        plots,
    })
}

fn score_run(truths: &[trn_flight::TimedPose], run: &RunInput, band_m: f64) -> Result<RunReport, EvalError> {
    let rows = trn_flight::read_nav_records(&run.poses)?;
    let (per_frame, ignored) = metrics::match_frames(truths, &rows);
    if ignored > 0 {
        tracing::info!("{}: {ignored} rows at no frame's time, ignored", run.poses.display());
    }
    let matches_path = match &run.matches {
        Some(p) => Some(p.clone()),
        None => {
            let p = run.poses.parent().unwrap_or(Path::new(".")).join("matches.csv");
            p.is_file().then_some(p)
        }
    };
    let residuals: Vec<f64> = match &matches_path {
        Some(p) => {
            trn_flight::read_match_records(p)?.iter().filter(|m| m.inlier).map(|m| m.residual_px).collect()
        }
        None => Vec::new(),
    };
    let cov_path = run.poses.parent().unwrap_or(Path::new(".")).join("covariance.csv");
    let cov_path = cov_path.is_file().then_some(cov_path);
    let consistency = match &cov_path {
        Some(p) => metrics::consistency(&per_frame, &trn_flight::read_pose_covariances(p)?),
        None => None,
    };
    let ms: Vec<f64> = per_frame.iter().filter_map(|f| f.ms).collect();
    Ok(RunReport {
        label: run.label.clone(),
        poses: run.poses.clone(),
        matches: matches_path,
        rows: rows.len(),
        rows_ignored: ignored,
        status: metrics::status_counts(&per_frame),
        fix_errors: metrics::fix_errors(&per_frame),
        pose_errors: metrics::pose_errors(&per_frame),
        bands: metrics::bands(&per_frame, band_m),
        timing_ms: metrics::stats(&ms),
        inlier_residual_px: metrics::stats(&residuals),
        covariance: cov_path,
        consistency,
        per_frame,
        inlier_residuals_px: residuals,
    })
}

/// Writes the evaluation as JSON, atomically.
pub fn write_json(path: &Path, e: &Evaluation) -> Result<(), EvalError> {
    let text = serde_json::to_string_pretty(e)
        .map_err(|err| EvalError::Output { path: path.to_path_buf(), reason: err.to_string() })?;
    trn_flight::write_atomic(path, |w| writeln!(w, "{text}"))?;
    Ok(())
}

fn pct(x: f64) -> String {
    format!("{:.1}%", 100.0 * x)
}

fn write_errors(f: &mut fmt::Formatter, title: &str, e: &Option<ErrorStats>) -> fmt::Result {
    let Some(e) = e else {
        return writeln!(f, "{title}: none");
    };
    writeln!(
        f,
        "{:<30}{:>12}{:>12}{:>12}{:>12}{:>12}",
        format!("{title} (n={})", e.n),
        "mean",
        "median",
        "p95",
        "max",
        "rms"
    )?;
    let rows: [(&str, &Stats, usize); 6] = [
        ("3D position (m)", &e.pos_m, 3),
        ("|east| (m)", &e.east_abs_m, 3),
        ("|north| (m)", &e.north_abs_m, 3),
        ("|up| (m)", &e.up_abs_m, 3),
        ("attitude (deg)", &e.att_deg, 4),
        ("boresight (deg)", &e.boresight_deg, 4),
    ];
    for (name, s, d) in rows {
        writeln!(
            f,
            "  {name:<28}{:>12.d$}{:>12.d$}{:>12.d$}{:>12.d$}{:>12.d$}",
            s.mean, s.median, s.p95, s.max, s.rms
        )?;
    }
    let [me, mn, mu] = e.enu_mean_m;
    writeln!(f, "  {:<28}{me:>12.3}{mn:>12.3}{mu:>12.3}", "mean east/north/up (m)")
}

impl fmt::Display for RunReport {
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        let s = &self.status;
        writeln!(
            f,
            "== run {} ({}): {} rows, {} at no frame's time (ignored)",
            self.label,
            self.poses.display(),
            self.rows,
            self.rows_ignored
        )?;
        writeln!(
            f,
            "frames {}: fix {} ({})  propagated {} ({})  lost {} ({}, {} without a row)",
            s.frames,
            pct(s.share_fix),
            s.fix,
            pct(s.share_propagated),
            s.propagated,
            pct(s.share_lost),
            s.lost,
            s.missing
        )?;
        write_errors(f, "errors, fix frames", &self.fix_errors)?;
        write_errors(f, "errors, fix + propagated", &self.pose_errors)?;
        writeln!(
            f,
            "{:<12}{:>8}{:>8}{:>8}{:>8}{:>12}{:>12}{:>12}{:>12}",
            "band", "frames", "fix", "prop", "lost", "3D mean", "3D median", "3D p95", "3D max"
        )?;
        for b in &self.bands {
            let c = &b.status;
            write!(
                f,
                "{:<12}{:>8}{:>8}{:>8}{:>8}",
                b.label,
                c.frames,
                pct(c.share_fix),
                pct(c.share_propagated),
                pct(c.share_lost)
            )?;
            match &b.fix_errors {
                Some(e) => writeln!(
                    f,
                    "{:>12.3}{:>12.3}{:>12.3}{:>12.3}",
                    e.pos_m.mean, e.pos_m.median, e.pos_m.p95, e.pos_m.max
                )?,
                None => writeln!(f, "{:>12}", "-")?,
            }
        }
        if let Some(t) = &self.timing_ms {
            writeln!(f, "time per row (ms): median {:.2}, p95 {:.2}, max {:.2}", t.median, t.p95, t.max)?;
        }
        if let Some(r) = &self.inlier_residual_px {
            writeln!(
                f,
                "inlier reprojection error (px, n={}): median {:.3}, p95 {:.3}, max {:.3}",
                r.n, r.median, r.p95, r.max
            )?;
        }
        if let Some(c) = &self.consistency {
            writeln!(
                f,
                "position covariance (NEES, n={}): mean {:.2} (consistent: {:.2}..{:.2}), {} within the 95% point, errors {:.1}x the reported sigma (median), the farthest fix {:.1} sigma from the truth (t {:.2} s)",
                c.fixes,
                c.mean_nees,
                c.band[0],
                c.band[1],
                pct(c.share_within_95),
                c.median_sigma_ratio,
                c.max_sigma_distance,
                c.max_sigma_distance_t
            )?;
            if let Some(a) = &c.attitude {
                writeln!(
                    f,
                    "attitude covariance (NEES, n={}): mean {:.2} (consistent: {:.2}..{:.2}), the farthest fix {:.1} sigma from the truth (t {:.2} s)",
                    a.fixes, a.mean_nees, a.band[0], a.band[1], a.max_sigma_distance, a.max_sigma_distance_t
                )?;
            }
        }
        Ok(())
    }
}

impl fmt::Display for Comparison {
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        writeln!(f, "== share of each run's rows with status fix, per altitude segment")?;
        let w = self.runs.iter().map(|r| r.len()).max().unwrap_or(0).max(18) + 2;
        write!(f, "{:<12}", "segment")?;
        for r in &self.runs {
            write!(f, "{r:>w$}")?;
        }
        writeln!(f)?;
        for s in &self.segments {
            write!(f, "{:<12}", s.label)?;
            for c in &s.cells {
                let cell = match c {
                    Some(c) => format!("{} ({}/{})", pct(c.share_fix), c.fix, c.rows),
                    None => "-".into(),
                };
                write!(f, "{cell:>w$}")?;
            }
            writeln!(f)?;
        }
        Ok(())
    }
}

impl fmt::Display for Evaluation {
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        writeln!(
            f,
            "flight {}: {} frames; bands of {} m; p95 = nearest rank",
            self.flight.display(),
            self.frames,
            self.band_m
        )?;
        for r in &self.runs {
            writeln!(f)?;
            write!(f, "{r}")?;
        }
        if let Some(c) = &self.comparison {
            writeln!(f)?;
            write!(f, "{c}")?;
        }
        Ok(())
    }
}

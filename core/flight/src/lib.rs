//! Flight logs in the project's format (`docs/FLIGHT_FORMAT.md`): what
//! `trn simulate` writes, `trn navigate` reads and `trn evaluate` scores.
//!
//! The main type is [`Flight`]: one camera's frames, the IMU samples, the
//! camera model and mounting, the initial pose guess and (when known) the
//! true trajectory, read from a flight folder with every file checked
//! (columns, numbers, increasing times, unit quaternions). Errors name the
//! file, the line and the field. [`NavRecord`] is a row of a navigator's
//! `poses.csv`; [`write_atomic`] and [`write_csv_atomic`] write files so that
//! nothing half-written is ever left under the final name.
//!
//! ```
//! use nalgebra::UnitQuaternion;
//! use trn_flight::{interpolate_pose, TimedPose};
//! use trn_geodesy::Geodetic;
//!
//! // Truth between two rows: linear in ECEF, slerp in attitude.
//! let q = UnitQuaternion::identity();
//! let rows = [
//!     TimedPose { t: 0.0, position: Geodetic::new(40.0, -111.0, 30_000.0), q_ecef_cam: q },
//!     TimedPose { t: 1.0, position: Geodetic::new(40.0, -111.0, 30_010.0), q_ecef_cam: q },
//! ];
//! let mid = interpolate_pose(&rows, 0.5).unwrap();
//! assert!((mid.position.h_m - 30_005.0).abs() < 1e-3);
//! assert!(interpolate_pose(&rows, 2.0).is_none());
//! ```

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::{UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use trn_camera::{quat_from_wxyz, quat_to_wxyz, CameraConfig};
use trn_geodesy::{Ecef, Geodetic};

/// An error reading or writing a flight file: the file, the line (1-based,
/// header = 1) when one is concerned, and what was wrong.
#[derive(Debug, thiserror::Error)]
#[error("{}{}: {reason}", path.display(), line.map(|l| format!(" line {l}")).unwrap_or_default())]
pub struct FlightError {
    pub path: PathBuf,
    pub line: Option<usize>,
    pub reason: String,
}

impl FlightError {
    pub fn new(path: &Path, line: Option<usize>, reason: impl Into<String>) -> Self {
        Self { path: path.to_path_buf(), line, reason: reason.into() }
    }
}

pub type Result<T> = std::result::Result<T, FlightError>;

/// One image of the flight (`frames.csv`).
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub t: f64,
    /// Path relative to the flight folder, as written in `frames.csv`.
    pub image: PathBuf,
}

/// One IMU sample (`imu.csv`): mean rates over the interval ending at `t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuSample {
    pub t: f64,
    /// Angular rate relative to inertial space, IMU frame (rad/s).
    pub w_imu_rad_s: Vector3<f64>,
    /// Specific force, IMU frame (m/s^2), when recorded.
    pub f_imu_m_s2: Option<Vector3<f64>>,
}

/// A camera pose at a time: position (WGS84 ellipsoidal) and `q_ecef_cam`
/// (`v_ecef = R(q) v_cam`). Rows of `truth.csv`, `init.json`, `poses.csv`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedPose {
    pub t: f64,
    pub position: Geodetic,
    pub q_ecef_cam: UnitQuaternion<f64>,
}

/// What the navigator made of a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FixStatus {
    /// Pose from PnP/RANSAC, accepted.
    Fix,
    /// No accepted fix; the pose was carried forward by the gyro.
    Propagated,
    /// No pose.
    Lost,
}

impl FixStatus {
    pub fn as_str(&self) -> &'static str {
        match self {
            FixStatus::Fix => "fix",
            FixStatus::Propagated => "propagated",
            FixStatus::Lost => "lost",
        }
    }

    fn parse(s: &str) -> Option<Self> {
        match s.trim() {
            "fix" => Some(FixStatus::Fix),
            "propagated" => Some(FixStatus::Propagated),
            "lost" => Some(FixStatus::Lost),
            _ => None,
        }
    }
}

/// One row of a navigator's `poses.csv`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NavRecord {
    pub pose: TimedPose,
    pub status: FixStatus,
    /// RANSAC inliers of the accepted or rejected solution.
    pub inliers: u32,
    /// Correlation matches passed to RANSAC.
    pub matches: u32,
    /// Wall time spent on the frame (ms).
    pub ms: f64,
}

/// `init.json`.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct InitJson {
    t: f64,
    lat: f64,
    lon: f64,
    h: f64,
    q_ecef_cam: [f64; 4],
}

/// A flight folder, read and checked.
#[derive(Clone, Debug)]
pub struct Flight {
    pub dir: PathBuf,
    pub camera: CameraConfig,
    pub frames: Vec<Frame>,
    pub imu: Vec<ImuSample>,
    pub init: TimedPose,
    /// `truth.csv`, when the flight has one.
    pub truth: Option<Vec<TimedPose>>,
}

pub const CAMERA_FILE: &str = "camera.json";
pub const FRAMES_FILE: &str = "frames.csv";
pub const IMU_FILE: &str = "imu.csv";
pub const INIT_FILE: &str = "init.json";
pub const TRUTH_FILE: &str = "truth.csv";

impl Flight {
    /// Reads every file of the flight folder `dir` (images are only checked
    /// to exist).
    pub fn open(dir: &Path) -> Result<Flight> {
        if !dir.is_dir() {
            return Err(FlightError::new(dir, None, "not a flight folder (no such directory)"));
        }
        let camera = read_camera(&dir.join(CAMERA_FILE))?;
        let frames = read_frames(&dir.join(FRAMES_FILE))?;
        for (i, f) in frames.iter().enumerate() {
            if !dir.join(&f.image).is_file() {
                return Err(FlightError::new(
                    &dir.join(FRAMES_FILE),
                    Some(i + 2),
                    format!("image {} does not exist", f.image.display()),
                ));
            }
        }
        let imu = read_imu(&dir.join(IMU_FILE))?;
        let init = read_init(&dir.join(INIT_FILE))?;
        let truth_path = dir.join(TRUTH_FILE);
        let truth = if truth_path.exists() { Some(read_poses_csv(&truth_path)?) } else { None };
        Ok(Flight { dir: dir.to_path_buf(), camera, frames, imu, init, truth })
    }

    /// The absolute path of a frame's image.
    pub fn image_path(&self, frame: &Frame) -> PathBuf {
        self.dir.join(&frame.image)
    }

    /// The true pose at time `t`: the row at `t` (within 1 µs), else the
    /// interpolation of the rows around it (linear in ECEF, slerp); `None`
    /// without truth or outside its time span.
    pub fn truth_at(&self, t: f64) -> Option<TimedPose> {
        interpolate_pose(self.truth.as_deref()?, t)
    }
}

/// Pose at `t` from rows sorted by time (see [`Flight::truth_at`]).
pub fn interpolate_pose(rows: &[TimedPose], t: f64) -> Option<TimedPose> {
    const EPS: f64 = 1e-6;
    let i = rows.partition_point(|r| r.t < t - EPS);
    let r1 = rows.get(i)?;
    if (r1.t - t).abs() <= EPS {
        return Some(*r1);
    }
    let r0 = rows.get(i.checked_sub(1)?)?;
    let s = (t - r0.t) / (r1.t - r0.t);
    let (p0, p1) = (r0.position.to_ecef().0, r1.position.to_ecef().0);
    let p = trn_geodesy::Ecef(p0 + (p1 - p0) * s).to_geodetic();
    Some(TimedPose { t, position: p, q_ecef_cam: r0.q_ecef_cam.slerp(&r1.q_ecef_cam, s) })
}

/// Reads `camera.json` and validates the model.
pub fn read_camera(path: &Path) -> Result<CameraConfig> {
    let text = read_text(path)?;
    let cfg: CameraConfig =
        serde_json::from_str(&text).map_err(|e| FlightError::new(path, Some(e.line()), e.to_string()))?;
    cfg.model.validate().map_err(|e| FlightError::new(path, None, e.to_string()))?;
    check_quat(path, None, "q_cam_imu", cfg.q_cam_imu)?;
    Ok(cfg)
}

/// Reads `init.json`.
pub fn read_init(path: &Path) -> Result<TimedPose> {
    let text = read_text(path)?;
    let j: InitJson =
        serde_json::from_str(&text).map_err(|e| FlightError::new(path, Some(e.line()), e.to_string()))?;
    check_position(path, None, j.lat, j.lon, j.h)?;
    check_quat(path, None, "q_ecef_cam", j.q_ecef_cam)?;
    Ok(TimedPose {
        t: j.t,
        position: Geodetic::new(j.lat, j.lon, j.h),
        q_ecef_cam: quat_from_wxyz(j.q_ecef_cam),
    })
}

fn read_text(path: &Path) -> Result<String> {
    fs::read_to_string(path).map_err(|e| FlightError::new(path, None, io_reason(&e)))
}

fn io_reason(e: &std::io::Error) -> String {
    match e.kind() {
        std::io::ErrorKind::NotFound => "no such file".into(),
        _ => e.to_string(),
    }
}

fn check_position(path: &Path, line: Option<usize>, lat: f64, lon: f64, h: f64) -> Result<()> {
    if !(-90.0..=90.0).contains(&lat) {
        return Err(FlightError::new(path, line, format!("lat {lat} is not a latitude in degrees")));
    }
    if !(-360.0..=360.0).contains(&lon) {
        return Err(FlightError::new(path, line, format!("lon {lon} is not a longitude in degrees")));
    }
    if !h.is_finite() || h.abs() > 1e7 {
        return Err(FlightError::new(path, line, format!("h {h} is not a height in metres")));
    }
    Ok(())
}

fn check_quat(path: &Path, line: Option<usize>, field: &str, q: [f64; 4]) -> Result<()> {
    let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    if !n.is_finite() || (n - 1.0).abs() > 1e-3 {
        return Err(FlightError::new(
            path,
            line,
            format!("{field} {q:?} is not a unit quaternion (norm {n})"),
        ));
    }
    Ok(())
}

/// A CSV file read by column name: extra columns are ignored, missing
/// required ones are reported by name.
struct Table {
    path: PathBuf,
    header: Vec<String>,
    rows: Vec<(usize, csv::StringRecord)>,
}

impl Table {
    fn read(path: &Path) -> Result<Table> {
        let file = fs::File::open(path).map_err(|e| FlightError::new(path, None, io_reason(&e)))?;
        let mut rdr = csv::ReaderBuilder::new().has_headers(true).trim(csv::Trim::All).from_reader(file);
        let header: Vec<String> = rdr
            .headers()
            .map_err(|e| FlightError::new(path, Some(1), e.to_string()))?
            .iter()
            .map(str::to_string)
            .collect();
        let mut rows = Vec::new();
        for (i, rec) in rdr.records().enumerate() {
            let line = i + 2;
            let rec = rec.map_err(|e| FlightError::new(path, Some(line), e.to_string()))?;
            rows.push((line, rec));
        }
        Ok(Table { path: path.to_path_buf(), header, rows })
    }

    fn column(&self, name: &str) -> Result<usize> {
        self.header.iter().position(|h| h == name).ok_or_else(|| {
            FlightError::new(
                &self.path,
                Some(1),
                format!("missing column {name:?} (header: {})", self.header.join(",")),
            )
        })
    }

    fn optional_column(&self, name: &str) -> Option<usize> {
        self.header.iter().position(|h| h == name)
    }

    fn text<'a>(&self, line: usize, rec: &'a csv::StringRecord, col: usize) -> Result<&'a str> {
        rec.get(col).ok_or_else(|| {
            FlightError::new(&self.path, Some(line), format!("missing field {:?}", self.header[col]))
        })
    }

    fn number(&self, line: usize, rec: &csv::StringRecord, col: usize) -> Result<f64> {
        let s = self.text(line, rec, col)?;
        let v: f64 = s.parse().map_err(|_| {
            FlightError::new(
                &self.path,
                Some(line),
                format!("field {:?}: {s:?} is not a number", self.header[col]),
            )
        })?;
        if !v.is_finite() {
            return Err(FlightError::new(
                &self.path,
                Some(line),
                format!("field {:?}: {s:?} is not finite", self.header[col]),
            ));
        }
        Ok(v)
    }

    /// `None` for an empty field.
    fn optional_number(&self, line: usize, rec: &csv::StringRecord, col: usize) -> Result<Option<f64>> {
        match rec.get(col) {
            None | Some("") => Ok(None),
            Some(_) => self.number(line, rec, col).map(Some),
        }
    }

    /// Checks that `t` increases strictly from row to row.
    fn check_increasing(&self, line: usize, prev: Option<f64>, t: f64) -> Result<()> {
        match prev {
            Some(p) if t <= p => Err(FlightError::new(
                &self.path,
                Some(line),
                format!("t {t} does not increase (previous row: {p})"),
            )),
            _ => Ok(()),
        }
    }
}

/// Reads `frames.csv`.
pub fn read_frames(path: &Path) -> Result<Vec<Frame>> {
    let tab = Table::read(path)?;
    let (ct, ci) = (tab.column("t")?, tab.column("image")?);
    let mut out: Vec<Frame> = Vec::with_capacity(tab.rows.len());
    for (line, rec) in &tab.rows {
        let t = tab.number(*line, rec, ct)?;
        tab.check_increasing(*line, out.last().map(|f| f.t), t)?;
        let image = tab.text(*line, rec, ci)?;
        if image.is_empty() || Path::new(image).is_absolute() || image.split(['/', '\\']).any(|c| c == "..") {
            return Err(FlightError::new(
                path,
                Some(*line),
                format!("image {image:?} must be a path inside the flight folder"),
            ));
        }
        out.push(Frame { t, image: PathBuf::from(image) });
    }
    if out.is_empty() {
        return Err(FlightError::new(path, None, "no frames"));
    }
    Ok(out)
}

/// Reads `imu.csv` (may have no rows).
pub fn read_imu(path: &Path) -> Result<Vec<ImuSample>> {
    let tab = Table::read(path)?;
    let ct = tab.column("t")?;
    let cw = [tab.column("wx")?, tab.column("wy")?, tab.column("wz")?];
    let ca = [tab.optional_column("ax"), tab.optional_column("ay"), tab.optional_column("az")];
    let mut out: Vec<ImuSample> = Vec::with_capacity(tab.rows.len());
    for (line, rec) in &tab.rows {
        let t = tab.number(*line, rec, ct)?;
        tab.check_increasing(*line, out.last().map(|s| s.t), t)?;
        let w = Vector3::new(
            tab.number(*line, rec, cw[0])?,
            tab.number(*line, rec, cw[1])?,
            tab.number(*line, rec, cw[2])?,
        );
        let mut a = [None; 3];
        for k in 0..3 {
            if let Some(c) = ca[k] {
                a[k] = tab.optional_number(*line, rec, c)?;
            }
        }
        let f = match a {
            [Some(x), Some(y), Some(z)] => Some(Vector3::new(x, y, z)),
            [None, None, None] => None,
            _ => {
                return Err(FlightError::new(
                    path,
                    Some(*line),
                    "ax, ay, az must be all present or all empty",
                ))
            }
        };
        out.push(ImuSample { t, w_imu_rad_s: w, f_imu_m_s2: f });
    }
    Ok(out)
}

/// Pose columns of `truth.csv` and `poses.csv`.
struct PoseColumns {
    t: usize,
    lat: usize,
    lon: usize,
    h: usize,
    q: [usize; 4],
}

impl PoseColumns {
    fn of(tab: &Table) -> Result<Self> {
        Ok(Self {
            t: tab.column("t")?,
            lat: tab.column("lat")?,
            lon: tab.column("lon")?,
            h: tab.column("h")?,
            q: [tab.column("qw")?, tab.column("qx")?, tab.column("qy")?, tab.column("qz")?],
        })
    }

    fn pose(&self, tab: &Table, line: usize, rec: &csv::StringRecord) -> Result<TimedPose> {
        let t = tab.number(line, rec, self.t)?;
        let (lat, lon, h) = (
            tab.number(line, rec, self.lat)?,
            tab.number(line, rec, self.lon)?,
            tab.number(line, rec, self.h)?,
        );
        check_position(&tab.path, Some(line), lat, lon, h)?;
        let mut q = [0.0; 4];
        for (v, &col) in q.iter_mut().zip(&self.q) {
            *v = tab.number(line, rec, col)?;
        }
        check_quat(&tab.path, Some(line), "qw,qx,qy,qz", q)?;
        Ok(TimedPose { t, position: Geodetic::new(lat, lon, h), q_ecef_cam: quat_from_wxyz(q) })
    }
}

/// Reads a `truth.csv`-style file (`t,lat,lon,h,qw,qx,qy,qz`).
pub fn read_poses_csv(path: &Path) -> Result<Vec<TimedPose>> {
    let tab = Table::read(path)?;
    let cols = PoseColumns::of(&tab)?;
    let mut out: Vec<TimedPose> = Vec::with_capacity(tab.rows.len());
    for (line, rec) in &tab.rows {
        let p = cols.pose(&tab, *line, rec)?;
        tab.check_increasing(*line, out.last().map(|r| r.t), p.t)?;
        out.push(p);
    }
    Ok(out)
}

/// Reads a navigator's `poses.csv`. Rows of status `lost` may carry empty
/// (or any) pose fields; their pose is then the previous row's, or NaN.
pub fn read_nav_records(path: &Path) -> Result<Vec<NavRecord>> {
    let tab = Table::read(path)?;
    let cols = PoseColumns::of(&tab)?;
    let (cs, ci, cm, cms) =
        (tab.column("status")?, tab.column("inliers")?, tab.column("matches")?, tab.column("ms")?);
    let mut out: Vec<NavRecord> = Vec::with_capacity(tab.rows.len());
    for (line, rec) in &tab.rows {
        let line = *line;
        let s = tab.text(line, rec, cs)?;
        let status = FixStatus::parse(s).ok_or_else(|| {
            FlightError::new(path, Some(line), format!("status {s:?} is not fix, propagated or lost"))
        })?;
        let t = tab.number(line, rec, cols.t)?;
        tab.check_increasing(line, out.last().map(|r| r.pose.t), t)?;
        let pose = if status == FixStatus::Lost {
            cols.pose(&tab, line, rec).unwrap_or(TimedPose {
                t,
                position: Geodetic::new(f64::NAN, f64::NAN, f64::NAN),
                q_ecef_cam: UnitQuaternion::identity(),
            })
        } else {
            cols.pose(&tab, line, rec)?
        };
        let count = |c: usize| -> Result<u32> {
            let v = tab.number(line, rec, c)?;
            if v < 0.0 || v.fract() != 0.0 || v > u32::MAX as f64 {
                return Err(FlightError::new(
                    path,
                    Some(line),
                    format!("field {:?}: {v} is not a count", tab.header[c]),
                ));
            }
            Ok(v as u32)
        };
        out.push(NavRecord {
            pose,
            status,
            inliers: count(ci)?,
            matches: count(cm)?,
            ms: tab.number(line, rec, cms)?,
        });
    }
    Ok(out)
}

/// Writes `path` through a temporary file in the same folder, renamed over
/// `path` only when `fill` succeeded.
pub fn write_atomic(path: &Path, fill: impl FnOnce(&mut dyn Write) -> std::io::Result<()>) -> Result<()> {
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let err = |e: std::io::Error| FlightError::new(path, None, e.to_string());
    if !dir.is_dir() {
        return Err(FlightError::new(path, None, format!("folder {} does not exist", dir.display())));
    }
    let mut tmp = tempfile::Builder::new().prefix(".trn-").suffix(".part").tempfile_in(dir).map_err(err)?;
    {
        let mut w = std::io::BufWriter::new(tmp.as_file_mut());
        fill(&mut w).map_err(err)?;
        w.flush().map_err(err)?;
    }
    // Temporary files are private (0600); the result is an ordinary file.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        tmp.as_file().set_permissions(fs::Permissions::from_mode(0o644)).map_err(err)?;
    }
    tmp.persist(path).map_err(|e| err(e.error))?;
    Ok(())
}

/// Writes CSV rows (header first) atomically.
pub fn write_csv_atomic(path: &Path, header: &str, rows: impl Iterator<Item = String>) -> Result<()> {
    write_atomic(path, |w| {
        writeln!(w, "{header}")?;
        for r in rows {
            writeln!(w, "{r}")?;
        }
        Ok(())
    })
}

pub fn write_camera(path: &Path, camera: &CameraConfig) -> Result<()> {
    let text =
        serde_json::to_string_pretty(camera).map_err(|e| FlightError::new(path, None, e.to_string()))?;
    write_atomic(path, |w| writeln!(w, "{text}"))
}

pub fn write_init(path: &Path, init: &TimedPose) -> Result<()> {
    let j = InitJson {
        t: init.t,
        lat: init.position.lat_deg,
        lon: init.position.lon_deg,
        h: init.position.h_m,
        q_ecef_cam: quat_to_wxyz(&init.q_ecef_cam),
    };
    let text = serde_json::to_string(&j).map_err(|e| FlightError::new(path, None, e.to_string()))?;
    write_atomic(path, |w| writeln!(w, "{text}"))
}

pub fn write_frames(path: &Path, frames: &[Frame]) -> Result<()> {
    write_csv_atomic(path, "t,image", frames.iter().map(|f| format!("{:.6},{}", f.t, f.image.display())))
}

pub fn write_imu(path: &Path, imu: &[ImuSample]) -> Result<()> {
    write_csv_atomic(
        path,
        "t,wx,wy,wz,ax,ay,az",
        imu.iter().map(|s| {
            let w = s.w_imu_rad_s;
            let a = s.f_imu_m_s2.map(|f| format!("{:.9},{:.9},{:.9}", f.x, f.y, f.z)).unwrap_or(",,".into());
            format!("{:.6},{:.12e},{:.12e},{:.12e},{a}", s.t, w.x, w.y, w.z)
        }),
    )
}

/// `t,lat,lon,h,qw,qx,qy,qz` with enough digits for sub-millimetre positions.
fn pose_fields(p: &TimedPose) -> String {
    let q = quat_to_wxyz(&p.q_ecef_cam);
    format!(
        "{:.6},{:.10},{:.10},{:.4},{:.12},{:.12},{:.12},{:.12}",
        p.t, p.position.lat_deg, p.position.lon_deg, p.position.h_m, q[0], q[1], q[2], q[3]
    )
}

pub const POSES_HEADER: &str = "t,lat,lon,h,qw,qx,qy,qz";
pub const NAV_HEADER: &str = "t,lat,lon,h,qw,qx,qy,qz,status,inliers,matches,ms";

pub fn write_truth(path: &Path, truth: &[TimedPose]) -> Result<()> {
    write_csv_atomic(path, POSES_HEADER, truth.iter().map(pose_fields))
}

/// One `poses.csv` row.
pub fn nav_record_line(r: &NavRecord) -> String {
    format!("{},{},{},{},{:.2}", pose_fields(&r.pose), r.status.as_str(), r.inliers, r.matches, r.ms)
}

/// Writes a navigator's `poses.csv` atomically.
pub fn write_nav_records(path: &Path, records: &[NavRecord]) -> Result<()> {
    write_csv_atomic(path, NAV_HEADER, records.iter().map(nav_record_line))
}

/// The covariance of an accepted fix (`covariance.csv`, written by the
/// navigator next to `poses.csv`): of the error `[dtheta; dp]`, attitude as a
/// rotation vector (rad, `q_true = exp(dtheta) q_est`) and position (m), both
/// in ECEF.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseCovariance {
    pub t: f64,
    /// Where the fix is (for the east/north/up standard deviations).
    pub position: Geodetic,
    pub ecef: nalgebra::Matrix6<f64>,
}

/// Standard deviations in the local frame, then the upper triangle of the
/// ECEF covariance row by row (`c_i_j`, i <= j; 0-2 attitude, 3-5 position).
pub fn covariance_header() -> String {
    let mut h = "t,sd_east_m,sd_north_m,sd_up_m,sd_att_east_deg,sd_att_north_deg,sd_att_up_deg".to_string();
    for i in 0..6 {
        for j in i..6 {
            h.push_str(&format!(",c_{i}_{j}"));
        }
    }
    h
}

pub fn pose_covariance_line(c: &PoseCovariance) -> String {
    let r = trn_geodesy::LocalFrame::at(c.position).r_ecef_enu();
    let att = r.transpose() * c.ecef.fixed_view::<3, 3>(0, 0) * r;
    let pos = r.transpose() * c.ecef.fixed_view::<3, 3>(3, 3) * r;
    let sd = |m: &nalgebra::Matrix3<f64>, i: usize| m[(i, i)].max(0.0).sqrt();
    let mut line = format!(
        "{:.6},{:.3},{:.3},{:.3},{:.6},{:.6},{:.6}",
        c.t,
        sd(&pos, 0),
        sd(&pos, 1),
        sd(&pos, 2),
        sd(&att, 0).to_degrees(),
        sd(&att, 1).to_degrees(),
        sd(&att, 2).to_degrees()
    );
    for i in 0..6 {
        for j in i..6 {
            line.push_str(&format!(",{:.6e}", c.ecef[(i, j)]));
        }
    }
    line
}

pub fn write_pose_covariances(path: &Path, rows: &[PoseCovariance]) -> Result<()> {
    write_csv_atomic(path, &covariance_header(), rows.iter().map(pose_covariance_line))
}

/// One `covariance.csv` row as read back: a fix's time and its ECEF
/// covariance (attitude rad² in 0..3, position m² in 3..6).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedCovariance {
    pub t: f64,
    pub ecef: nalgebra::Matrix6<f64>,
}

/// Reads `covariance.csv` ([`write_pose_covariances`]).
pub fn read_pose_covariances(path: &Path) -> Result<Vec<TimedCovariance>> {
    let tab = Table::read(path)?;
    let t = tab.column("t")?;
    let mut cols = Vec::with_capacity(21);
    for i in 0..6 {
        for j in i..6 {
            cols.push((i, j, tab.column(&format!("c_{i}_{j}"))?));
        }
    }
    let mut out = Vec::with_capacity(tab.rows.len());
    for (line, rec) in &tab.rows {
        let mut m = nalgebra::Matrix6::zeros();
        for &(i, j, k) in &cols {
            let v = tab.number(*line, rec, k)?;
            m[(i, j)] = v;
            m[(j, i)] = v;
        }
        out.push(TimedCovariance { t: tab.number(*line, rec, t)?, ecef: m });
    }
    Ok(out)
}

/// One correlation match of a processed frame (`matches.csv`, written by the
/// navigator next to `poses.csv`; not part of the shared flight format).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MatchRecord {
    /// Frame time.
    pub t: f64,
    /// Landmark (template) id in the database.
    pub landmark: i64,
    /// Where correlation found the landmark, pixel (u, v).
    pub u: f64,
    pub v: f64,
    /// Where the final pose projects the landmark, pixel (u, v).
    pub pred_u: f64,
    pub pred_v: f64,
    /// Reprojection error under the final pose (px).
    pub residual_px: f64,
    pub inlier: bool,
    /// The landmark's 3D position (ECEF), so a filter or smoother can use the
    /// matches without the database (columns `x_m,y_m,z_m`, empty if unknown).
    pub landmark_ecef: Option<Ecef>,
    /// 1-sigma of where correlation found the landmark (px), from the NCC
    /// peak's height and curvature (column `sigma_px`, empty if unknown).
    pub sigma_px: Option<f64>,
}

pub const MATCHES_HEADER: &str = "t,landmark,u,v,pred_u,pred_v,residual_px,inlier,x_m,y_m,z_m,sigma_px";

pub fn match_record_line(m: &MatchRecord) -> String {
    let xyz = m.landmark_ecef.map_or(",,".to_string(), |p| format!("{:.3},{:.3},{:.3}", p.0.x, p.0.y, p.0.z));
    let sigma = m.sigma_px.map_or(String::new(), |s| format!("{s:.4}"));
    format!(
        "{:.6},{},{:.3},{:.3},{:.3},{:.3},{:.4},{},{xyz},{sigma}",
        m.t, m.landmark, m.u, m.v, m.pred_u, m.pred_v, m.residual_px, m.inlier as u8
    )
}

pub fn write_match_records(path: &Path, records: &[MatchRecord]) -> Result<()> {
    write_csv_atomic(path, MATCHES_HEADER, records.iter().map(match_record_line))
}

/// Reads a navigator's `matches.csv` (times may repeat: many matches per frame).
pub fn read_match_records(path: &Path) -> Result<Vec<MatchRecord>> {
    let tab = Table::read(path)?;
    let c: Vec<usize> = ["t", "landmark", "u", "v", "pred_u", "pred_v", "residual_px", "inlier"]
        .iter()
        .map(|n| tab.column(n))
        .collect::<Result<_>>()?;
    // Files written before the landmark columns have none.
    let xyz: Option<Vec<usize>> = ["x_m", "y_m", "z_m"].iter().map(|n| tab.optional_column(n)).collect();
    let sigma_col = tab.optional_column("sigma_px");
    let mut out = Vec::with_capacity(tab.rows.len());
    for (line, rec) in &tab.rows {
        let n = |k: usize| tab.number(*line, rec, c[k]);
        let landmark_ecef = match &xyz {
            Some(x) => {
                let v: Vec<Option<f64>> =
                    x.iter().map(|&k| tab.optional_number(*line, rec, k)).collect::<Result<_>>()?;
                match (v[0], v[1], v[2]) {
                    (Some(a), Some(b), Some(c)) => Some(Ecef::new(a, b, c)),
                    (None, None, None) => None,
                    _ => {
                        return Err(FlightError::new(
                            path,
                            Some(*line),
                            "fields x_m, y_m, z_m: give all three or none".to_string(),
                        ))
                    }
                }
            }
            None => None,
        };
        let landmark = n(1)?;
        let inlier = match n(7)? {
            0.0 => false,
            1.0 => true,
            v => {
                return Err(FlightError::new(
                    path,
                    Some(*line),
                    format!("field \"inlier\": {v} is not 0 or 1"),
                ))
            }
        };
        out.push(MatchRecord {
            t: n(0)?,
            landmark: landmark as i64,
            u: n(2)?,
            v: n(3)?,
            pred_u: n(4)?,
            pred_v: n(5)?,
            residual_px: n(6)?,
            inlier,
            landmark_ecef,
            sigma_px: match sigma_col {
                Some(k) => tab.optional_number(*line, rec, k)?,
                None => None,
            },
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(t: f64) -> TimedPose {
        TimedPose {
            t,
            position: Geodetic::new(40.1 + t * 1e-4, -105.2, 30000.0 - t),
            q_ecef_cam: UnitQuaternion::from_euler_angles(0.1 * t, 0.2, -0.3),
        }
    }

    #[test]
    fn poses_round_trip_below_a_millimetre() {
        let dir = tempfile::tempdir().unwrap();
        let truth: Vec<TimedPose> = (0..5).map(|i| pose(i as f64 * 0.25)).collect();
        let path = dir.path().join("truth.csv");
        write_truth(&path, &truth).unwrap();
        let back = read_poses_csv(&path).unwrap();
        assert_eq!(back.len(), truth.len());
        for (a, b) in truth.iter().zip(&back) {
            assert!(a.position.to_ecef().distance_m(&b.position.to_ecef()) < 1e-3);
            assert!(a.q_ecef_cam.angle_to(&b.q_ecef_cam) < 1e-10);
        }
    }

    #[test]
    fn nav_records_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let recs = vec![
            NavRecord { pose: pose(0.0), status: FixStatus::Fix, inliers: 12, matches: 20, ms: 3.5 },
            NavRecord { pose: pose(0.5), status: FixStatus::Propagated, inliers: 3, matches: 9, ms: 1.25 },
        ];
        let path = dir.path().join("poses.csv");
        write_nav_records(&path, &recs).unwrap();
        let back = read_nav_records(&path).unwrap();
        assert_eq!(back[1].status, FixStatus::Propagated);
        assert_eq!((back[0].inliers, back[0].matches), (12, 20));
        assert!((back[1].ms - 1.25).abs() < 1e-9);
    }

    #[test]
    fn bad_rows_name_file_line_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("imu.csv");
        fs::write(&path, "t,wx,wy,wz\n0.0,0,0,0\n0.1,0,abc,0\n").unwrap();
        let e = read_imu(&path).unwrap_err().to_string();
        assert!(e.contains("imu.csv line 3") && e.contains("\"wy\""), "{e}");
        fs::write(&path, "t,wx,wy\n").unwrap();
        let e = read_imu(&path).unwrap_err().to_string();
        assert!(e.contains("missing column \"wz\""), "{e}");
        fs::write(&path, "t,wx,wy,wz\n0.2,0,0,0\n0.1,0,0,0\n").unwrap();
        let e = read_imu(&path).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("does not increase"), "{e}");
        let truth = dir.path().join("truth.csv");
        fs::write(&truth, "t,lat,lon,h,qw,qx,qy,qz\n0,40,-105,100,2,0,0,0\n").unwrap();
        let e = read_poses_csv(&truth).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("unit quaternion"), "{e}");
        let frames = dir.path().join("frames.csv");
        fs::write(&frames, "t,image\n0,../x.png\n").unwrap();
        let e = read_frames(&frames).unwrap_err().to_string();
        assert!(e.contains("inside the flight folder"), "{e}");
    }

    #[test]
    fn imu_accelerometer_columns_are_optional() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("imu.csv");
        let s = [
            ImuSample { t: 0.0, w_imu_rad_s: Vector3::new(1e-5, 2e-5, -3e-5), f_imu_m_s2: None },
            ImuSample {
                t: 0.005,
                w_imu_rad_s: Vector3::new(0.1, 0.0, 0.0),
                f_imu_m_s2: Some(Vector3::z() * 9.8),
            },
        ];
        write_imu(&path, &s).unwrap();
        let back = read_imu(&path).unwrap();
        assert_eq!(back[0].f_imu_m_s2, None);
        assert!((back[1].f_imu_m_s2.unwrap().z - 9.8).abs() < 1e-9);
        assert!((back[0].w_imu_rad_s - s[0].w_imu_rad_s).norm() < 1e-15);
    }

    #[test]
    fn interpolation_hits_rows_and_between() {
        let rows: Vec<TimedPose> = (0..3).map(|i| pose(i as f64)).collect();
        assert_eq!(interpolate_pose(&rows, 1.0).unwrap().position, rows[1].position);
        let mid = interpolate_pose(&rows, 0.5).unwrap();
        let d0 = mid.position.to_ecef().distance_m(&rows[0].position.to_ecef());
        let d1 = mid.position.to_ecef().distance_m(&rows[1].position.to_ecef());
        assert!((d0 - d1).abs() < 1e-6);
        assert!(interpolate_pose(&rows, 2.5).is_none());
        assert!(interpolate_pose(&rows, -0.1).is_none());
    }

    #[test]
    fn matches_round_trip_with_and_without_landmark_positions() {
        let dir = tempfile::tempdir().unwrap();
        let m = |landmark_ecef, sigma_px| MatchRecord {
            t: 0.25,
            landmark: 7,
            u: 10.5,
            v: 20.25,
            pred_u: 10.0,
            pred_v: 20.0,
            residual_px: 0.559,
            inlier: true,
            landmark_ecef,
            sigma_px,
        };
        let rows = [m(Some(Ecef::new(-1284512.125, -4716392.5, 4079688.0)), Some(0.0625)), m(None, None)];
        let path = dir.path().join("matches.csv");
        write_match_records(&path, &rows).unwrap();
        assert_eq!(read_match_records(&path).unwrap(), rows);
        // Files from before the landmark columns still read.
        std::fs::write(
            &path,
            "t,landmark,u,v,pred_u,pred_v,residual_px,inlier\n0.25,7,10.5,20.25,10,20,0.559,1\n",
        )
        .unwrap();
        assert_eq!(read_match_records(&path).unwrap(), vec![m(None, None)]);
        // Half a position is an error that names the fields.
        std::fs::write(&path, format!("{MATCHES_HEADER}\n0.25,7,10.5,20.25,10,20,0.559,1,1,2,,\n")).unwrap();
        let e = read_match_records(&path).unwrap_err().to_string();
        assert!(e.contains("x_m, y_m, z_m") && e.contains("matches.csv"), "{e}");
    }

    #[test]
    fn covariance_rows_give_local_standard_deviations() {
        // 1 m^2 east only, at the equator / prime meridian (east = ECEF y).
        let mut ecef = nalgebra::Matrix6::zeros();
        ecef[(4, 4)] = 4.0;
        ecef[(2, 2)] = 1e-6;
        let c = PoseCovariance { t: 1.0, position: Geodetic::new(0.0, 0.0, 100.0), ecef };
        let line = pose_covariance_line(&c);
        let v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        assert_eq!(v.len(), covariance_header().split(',').count());
        assert!((v[1] - 2.0).abs() < 1e-9 && v[2].abs() < 1e-9 && v[3].abs() < 1e-9, "{line}");
        // ECEF z at the equator is north.
        assert!((v[5] - 1e-3f64.to_degrees()).abs() < 1e-6, "{line}");
    }
}

//! `trn`: the command line of the landmark system. Parsing and option checks
//! live here; each subcommand calls one product (`trn build`: trn-builder,
//! `trn serve` and `trn coverage`: trn-server, `trn navigate`: trn-navigator)
//! or tool (`trn simulate`, `trn degrade-dem`: trn-sim; `trn evaluate`: trn-eval).

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand, ValueEnum};
use tracing_subscriber::EnvFilter;
use trn_builder::{BuildOptions, DemVertical};

// Tiles allocate large short-lived buffers; glibc would hand each back to the
// kernel and fault it in again.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
#[command(
    name = "trn",
    version,
    about = "Landmark database, server and navigator for terrain relative navigation"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

impl Cli {
    /// The command line as clap reads it, but that a negative number after
    /// an option is that option's value: `--miss-min-cells -1` is then
    /// refused as the option's invalid value, naming it, where clap took
    /// `-1` for an unknown flag and named no option; and an option whose
    /// negative values mean something (`trn synth --east -500`) takes
    /// them without `=`.
    fn command_line() -> clap::Command {
        Self::command().mut_subcommands(|sub| {
            sub.mut_args(
                |arg| if arg.get_action().takes_values() { arg.allow_negative_numbers(true) } else { arg },
            )
        })
    }

    /// [`Cli::command_line`] parsed from `args` (the program's name first).
    fn try_parse_args<I, T>(args: I) -> Result<Self, clap::Error>
    where
        I: IntoIterator<Item = T>,
        T: Into<std::ffi::OsString> + Clone,
    {
        Self::command_line().try_get_matches_from(args).and_then(|m| Self::from_arg_matches(&m))
    }
}

#[derive(Subcommand)]
enum Command {
    /// Cut orthoimagery and DEMs into a landmark database (SQLite/GeoPackage).
    Build(BuildArgs),
    /// Write a synthetic ortho + DEM pair (GeoTIFF) for tests and benchmarks.
    Synth(SynthArgs),
    /// Write a coarser and/or noisier copy of a DEM, for a database whose relief is not the rendered one.
    DegradeDem(DegradeDemArgs),
    /// Simulate a flight over an ortho + DEM: camera images, IMU, truth (flight format).
    Simulate(SimulateArgs),
    /// Navigate a flight against a landmark database: one pose per processed image.
    Navigate(NavigateArgs),
    /// Score navigator poses.csv files against a flight's truth.csv (tables, JSON, plots).
    Evaluate(EvaluateArgs),
    /// Serve a landmark database over HTTP (bounding-box, footprint and coverage queries).
    Serve(ServeArgs),
    /// Usable landmarks along a planned trajectory: JSON report, GeoJSON, PNG map.
    Coverage(CoverageArgs),
}

#[derive(Clone, Copy, ValueEnum)]
enum VerticalArg {
    /// Heights above the EGM96 geoid (mean sea level), converted with EGM96.
    Egm96,
    /// Heights already above the WGS84 ellipsoid.
    Ellipsoid,
    /// Heights above the geoid given by --geoid GRID (e.g. GEOID18 for NAVD88).
    Geoid,
}

/// The elevation models, as `trn build` and `trn simulate` take them
/// ([`trn_raster::DemInputs`]).
#[derive(clap::Args, Clone)]
struct DemArgs {
    /// Elevation model(s): any GDAL raster, any CRS; tiles of one grid are read as one mosaic.
    #[arg(long = "dem", required = true, num_args = 1..)]
    dems: Vec<PathBuf>,
    /// Vertical datum of the DEM heights when the file does not say (or to override it).
    #[arg(long, value_enum)]
    dem_vertical: Option<VerticalArg>,
    /// Geoid grid (GDAL-readable: .gtx, .tif) for --dem-vertical geoid; default for EGM96 is Debian's.
    #[arg(long)]
    geoid: Option<PathBuf>,
}

impl DemArgs {
    fn inputs(self) -> trn_raster::DemInputs {
        let vertical = self.dem_vertical.map(|v| match v {
            VerticalArg::Egm96 => DemVertical::Egm96,
            VerticalArg::Ellipsoid => DemVertical::Ellipsoid,
            VerticalArg::Geoid => DemVertical::Geoid,
        });
        trn_raster::DemInputs { files: self.dems, vertical, geoid: self.geoid }
    }
}

#[derive(clap::Args)]
struct BuildArgs {
    /// Orthoimage(s): any GDAL raster, any CRS; several files form a mosaic.
    #[arg(long = "ortho", required = true, num_args = 1..)]
    orthos: Vec<PathBuf>,
    #[command(flatten)]
    dem: DemArgs,
    /// Output database (replaced atomically when the build succeeds).
    #[arg(long)]
    out: PathBuf,
    /// Bands making the luminance: one (grey) or three (red,green,blue), e.g. 3,2,1.
    #[arg(long, value_delimiter = ',')]
    ortho_bands: Option<Vec<usize>>,
    /// Largest template side in pixels (coarse levels).
    #[arg(long, default_value_t = 32)]
    template_size: u32,
    /// Smallest template side: the finest level holds half-size templates at
    /// the ortho's resolution when they are at least this big.
    #[arg(long, default_value_t = 12)]
    min_template_size: u32,
    /// Landmark spacing: one cell of this many template pixels gets
    /// --per-cell landmarks (default: the level's template size; with
    /// --camera, what puts at least ~120 cells in the camera's view, 0.5-1 size).
    #[arg(long)]
    spacing: Option<u32>,
    #[arg(long, default_value_t = 1)]
    per_cell: usize,
    /// Density fill: where fewer than this share of the ~120 cells a camera
    /// sees around a cell kept a landmark (water, bare ground), textured cells
    /// keep up to 4x --per-cell (a --camera that sees more cells: its view,
    /// and as many landmarks); 0: off (default: 0.7 with --camera; without
    /// it, 0.7 on a finest level whose ortho is too coarse for the lowest
    /// cameras, off on the others).
    #[arg(long)]
    fill_share: Option<f32>,
    /// Number of levels (template footprint doubles per level); default: as
    /// many as the served camera resolutions need.
    #[arg(long)]
    levels: Option<u8>,
    /// GSD of the finest pyramid step (m); default: the coarsest ortho pixel size.
    #[arg(long)]
    base_gsd: Option<f64>,
    /// Size the database for this camera (camera.json of the flight format)
    /// flown at --altitude; default: cameras of 160x120 to 1024x768 pixels,
    /// 20-60 deg fields of view, 2-40 km above the terrain.
    #[arg(long)]
    camera: Option<PathBuf>,
    /// Heights above the terrain the mission flies, MIN..MAX metres (with --camera).
    #[arg(long, value_parser = parse_altitude)]
    altitude: Option<(f64, f64)>,
    /// Largest angle of the camera's boresight from straight down (deg, with
    /// --camera; default 0).
    #[arg(long)]
    max_off_nadir: Option<f64>,
    /// A planned trajectory (the JSON of `trn coverage --plan`): the report then
    /// gives the landmarks in view at each of its points and the stretches below
    /// the plan's threshold, in the new database.
    #[arg(long)]
    coverage_plan: Option<PathBuf>,
    /// Minimum grey-level standard deviation of a template.
    #[arg(long, default_value_t = 4.0)]
    min_contrast: f32,
    /// Minimum Shi-Tomasi strength (smaller structure-tensor eigenvalue).
    #[arg(long, default_value_t = 1.0)]
    min_shi_tomasi: f32,
    /// Uniqueness search radius (template pixels).
    #[arg(long, default_value_t = 8)]
    search_radius: u32,
    /// Highest NCC of a template against its surroundings (away from itself).
    #[arg(long, default_value_t = 0.9)]
    max_second_peak: f32,
    /// Largest RMS terrain distance from the template plane, in GSDs
    /// (default: none; relief is modelled by the template's height grid).
    #[arg(long)]
    max_relief: Option<f64>,
    /// Largest share of a template its own relief may hide at the served
    /// view angles (self-occlusion).
    #[arg(long, default_value_t = 0.5)]
    max_hidden: f64,
    /// Bake a sun into the templates: AZ,EL degrees (azimuth clockwise from
    /// north, elevation above the horizon), optionally ,DIFFUSE (share of
    /// sky light, default 0.25). Shading and cast shadows from the DEM are
    /// rendered onto the ortho; repeat for several suns (each landmark is
    /// then stored once per sun, and navigators pick theirs with --sun).
    #[arg(long = "sun", value_parser = parse_sun)]
    suns: Vec<trn_landmark::lighting::SunLight>,
    /// Reject templates whose shading share (how much of their contrast
    /// relief shading could make, 0..1) is above this: the cell takes its
    /// next candidate (default: no limit).
    #[arg(long)]
    max_shading: Option<f64>,
    /// Worker threads (default: all cores).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
}

#[derive(clap::Args)]
struct DegradeDemArgs {
    /// Elevation model to degrade (any GDAL raster; band 1).
    #[arg(long)]
    dem: PathBuf,
    /// Output GeoTIFF (Float32, the input's CRS and nodata; written atomically).
    #[arg(long)]
    out: PathBuf,
    /// Output cell size (m): block averages of round(cell / input cell) cells. Default: the input's grid.
    #[arg(long)]
    cell_m: Option<f64>,
    /// RMS of the added correlated noise (m).
    #[arg(long, default_value_t = 0.0)]
    noise_m: f64,
    /// Correlation length of the noise (m): sigma of the Gaussian that smooths white noise.
    #[arg(long, default_value_t = 300.0)]
    noise_scale_m: f64,
    /// Seed of the noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

#[derive(clap::Args)]
struct SynthArgs {
    /// Output ortho (GeoTIFF).
    #[arg(long)]
    ortho: PathBuf,
    /// Output DEM (GeoTIFF, ellipsoidal heights).
    #[arg(long)]
    dem: PathBuf,
    /// Ortho size in pixels (square).
    #[arg(long, default_value_t = 2048)]
    size: usize,
    /// Ortho pixel size (m).
    #[arg(long, default_value_t = 2.0)]
    gsd: f64,
    /// UTM zone 13N easting/northing of the top-left corner.
    #[arg(long, default_value_t = 440000.0)]
    east: f64,
    #[arg(long, default_value_t = 4460000.0)]
    north: f64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Ortho compression: deflate (lossless) or jpeg (YCbCr q90, as USGS NAIP).
    #[arg(long, value_enum, default_value_t = CompressArg::Deflate)]
    compress: CompressArg,
    /// Width of a nodata frame around the ortho (pixels).
    #[arg(long, default_value_t = 0)]
    nodata_border: usize,
    /// Terrain relief of the DEM (m, amplitude of the fractal heights above 1500 m).
    #[arg(long, default_value_t = 60.0)]
    relief: f64,
}

#[derive(clap::Args)]
struct SimulateArgs {
    /// Orthoimage the camera sees (any GDAL raster, any CRS).
    #[arg(long)]
    ortho: PathBuf,
    #[command(flatten)]
    dem: DemArgs,
    /// Scenario (JSON): trajectory, camera, IMU, initial error, realism.
    #[arg(long)]
    scenario: PathBuf,
    /// Output flight folder (replaced atomically when the simulation succeeds).
    #[arg(long)]
    out: PathBuf,
    /// Bands making the luminance, e.g. 3,2,1 (as trn build).
    #[arg(long, value_delimiter = ',')]
    ortho_bands: Option<Vec<usize>>,
    /// Stop the flight after this many seconds.
    #[arg(long)]
    duration: Option<f64>,
    /// Worker threads (default: all cores).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
}

#[derive(clap::Args)]
struct NavigateArgs {
    /// Landmark database (from trn build).
    #[arg(long, required_unless_present = "server", conflicts_with = "server")]
    db: Option<PathBuf>,
    /// Landmark server (trn serve) instead of --db, e.g. http://127.0.0.1:8080.
    #[arg(long)]
    server: Option<String>,
    /// Flight folder (flight format).
    #[arg(long)]
    flight: PathBuf,
    /// Output poses.csv (matches.csv and covariance.csv are written next to it).
    #[arg(long)]
    out: PathBuf,
    /// Images per second taken from the flight (default: every image).
    #[arg(long)]
    rate: Option<f64>,
    /// Do not carry the attitude with the gyro between images.
    #[arg(long)]
    no_gyro: bool,
    /// Largest angle between a line of sight and the surface normal (deg).
    #[arg(long, default_value_t = 75.0)]
    alpha_max: f64,
    /// Fewer RANSAC inliers reject the fix.
    #[arg(long, default_value_t = 8)]
    min_inliers: usize,
    /// RANSAC's inlier threshold (px at full resolution; a coarse pyramid
    /// level's scaled with it): a match farther than this from the pose's
    /// projection of its landmark is an outlier.
    #[arg(long, default_value_t = 3.0)]
    ransac_threshold: f64,
    /// Inliers a smaller share of the correlation matches than this reject the
    /// fix (a chance consensus of wrong matches; 0.3 before the RANSAC
    /// threshold went from 2 to 3 px, whose wider band admits more of them).
    #[arg(long, default_value_t = 0.45, value_parser = parse_share)]
    min_inlier_share: f64,
    /// A fix whose height is farther than this from the predicted one (the
    /// last fix carried by the vertical velocity) rejects it (m); the gate
    /// widens by 3 sigma of the vertical velocity per second since that fix.
    #[arg(long, default_value_t = 450.0)]
    max_height_jump: f64,
    /// Landmarks correlated per image (spread over it, near duplicates last).
    #[arg(long, default_value_t = 600)]
    max_landmarks: usize,
    /// Threads a frame's landmarks are predicted and correlated on. The
    /// poses are the same for any count; 1 (the default) keeps the navigator
    /// on one core, beside the rest of a flight's software, as its
    /// benchmarks measure it.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: u32,
    /// Correlation work per lost frame (G multiply-adds, a template's warp
    /// counting 0.01, each search position 400 more) when the guess's uncertainty is wider than one search
    /// reaches (a low camera kilometres off): tiles around the guess are
    /// searched nearest first until it is spent. 30 is about a second on one
    /// core.
    #[arg(long, default_value_t = 30.0)]
    acquisition_budget: f64,
    /// Position uncertainty of init.json (m, 1 sigma): the first search's radius
    /// and the first fix's height check.
    #[arg(long, default_value_t = 300.0)]
    init_sigma_m: f64,
    /// Attitude uncertainty of init.json (deg, 1 sigma).
    #[arg(long, default_value_t = 2.0)]
    init_sigma_deg: f64,
    /// Gyro angle random walk assumed by the attitude filter (deg/sqrt(h), 1 sigma).
    #[arg(long, default_value_t = 0.3)]
    gyro_arw: f64,
    /// Gyro bias uncertainty assumed by the attitude filter at the start (deg/h, 1 sigma).
    #[arg(long, default_value_t = 20.0)]
    gyro_bias: f64,
    /// A gyro rate that jumps by more than this from one sample to the next
    /// (deg/s; 0: never) is doubted (by the inertial filter, or with
    /// --filter fixes by the attitude's): the angle it turns beyond the rate
    /// before widens the attitude's uncertainty (up to 10 deg), and a frame
    /// that does not fix after it is searched again with the turn undone
    /// (a glitch, not a turn; the report's gyro_jumps_undone).
    #[arg(long, default_value_t = 10.0)]
    gyro_max_jump: f64,
    /// A specific force that jumps by more than this from one accelerometer
    /// sample to the next (m/s^2; 0: never) is doubted by the inertial
    /// filter: the velocity it adds beyond the force before (for 2 s at most)
    /// widens the velocity's uncertainty.
    #[arg(long, default_value_t = 10.0)]
    accel_max_jump: f64,
    /// Through a gap in imu.csv (an interval over 5 times its median), the
    /// doubt on the rate interpolated between the samples either side
    /// (deg/s/sqrt(s), a random walk; 0: none): the attitude's sigma grows as
    /// DOUBT * sqrt(t^3 / 3) t seconds into the gap, up to 10 deg; the fixes
    /// in the gap learn the rate. Likewise before the log's first sample
    /// and after its last. (With --filter fixes, nothing learns the rate
    /// in a gap or before the log: the attitude's doubt there grows from
    /// the stretch's start; after the log two fixes measure it.)
    #[arg(long, default_value_t = 3.0)]
    imu_gap_doubt: f64,
    /// The gyro's measurement range per axis (deg/s): a sample beyond it is
    /// no measurement (a corrupt record) and is left out, reported; the
    /// default is beyond any gyro flown.
    #[arg(long, default_value_t = trn_navigator::nav::DEFAULT_GYRO_RANGE_DEG_S)]
    gyro_range: f64,
    /// The accelerometer's measurement range per axis (m/s^2), as
    /// --gyro-range's.
    #[arg(long, default_value_t = trn_navigator::nav::DEFAULT_ACCEL_RANGE_M_S2)]
    accel_range: f64,
    /// Write a picture per processed frame here: inliers green, outliers red,
    /// where the pose guess predicted each landmark blue with a line to the match.
    #[arg(long)]
    matches_dir: Option<PathBuf>,
    /// Also write the inertial filter's pose at every IMU sample:
    /// poses-imu.csv and covariance-imu.csv next to --out (poses.csv's and
    /// covariance.csv's columns; between frames the status is `propagated`).
    #[arg(long)]
    imu_rate: bool,
    /// The sun during the flight, AZ,EL degrees: with a database built with
    /// several `--sun`s, the templates baked under the nearest are used
    /// (default: its first sun).
    #[arg(long, value_parser = parse_sun)]
    sun: Option<trn_landmark::lighting::SunLight>,
    /// Weight of a template's shading share in the choice of landmarks when
    /// the database's lighting is not the flight's sun (0: ignored).
    #[arg(long, default_value_t = 0.5, value_parser = parse_share)]
    shading_weight: f64,
    /// Landmarks closer on the ground than this share of a template's
    /// footprint to a better one in the same image cell are near duplicates
    /// (most of their pixels the same), taken only after the others
    /// (0: off).
    #[arg(long, default_value_t = 0.5, value_parser = parse_share)]
    duplicate_separation: f64,
    /// How the matches meet the inertial sensors: `tight` (an inertial
    /// filter updated with each frame's matches), `loose` (updated with each
    /// frame's image-only pose) or `fixes` (no inertial filter: each
    /// frame's pose is its own fix, the gyro carries the attitude; the
    /// navigator before the filter, for comparison: it doubts time without
    /// IMU samples, the gyro's jumps and runs of misses, and reads no
    /// accelerometer; a fix's covariance is scaled by its residuals and
    /// counts the map offset's prior, which the filter carries as states).
    #[arg(long, value_enum, default_value_t = FilterArg::Tight)]
    filter: FilterArg,
    /// Velocity uncertainty at the start (m/s, 1 sigma per axis; init.json
    /// gives no velocity).
    #[arg(long, default_value_t = 300.0)]
    init_velocity_sigma: f64,
    /// Accelerometer bias uncertainty at the start (m/s^2, 1 sigma).
    #[arg(long, default_value_t = 0.05)]
    accel_bias: f64,
    /// Map offset of the inertial filter: how far the database's errors
    /// shift the fixes from the same landmarks (m, 1 sigma per axis; 0: not
    /// modelled; default: 4/3 of the inliers' ground sample distance, 40 m
    /// for a 30 m ortho) ...
    #[arg(long)]
    map_sigma: Option<f64>,
    /// ... and how long that shift stays alike (s).
    #[arg(long, default_value_t = 10.0)]
    map_tau: f64,
    /// ... and the rotation they give the pose the images see (deg, 1 sigma
    /// per axis; 0: not modelled; default: 0.1 per 30 m of the inliers'
    /// ground sample distance): a narrow view trades a tilt for a shift.
    #[arg(long)]
    map_att_sigma: Option<f64>,
    /// ... and each landmark's own error, alike in every image that sees it
    /// (px, 1 sigma; 0: not modelled): what it gives the pose of a fix's
    /// view beyond the offset above (up to 5 of its sigmas) joins the
    /// offset, so a narrow view's fixes, whose few landmarks trade a tilt
    /// for a shift, move the offset and not the pose (0.5 keeps the fixes
    /// of a hole in the cloud nearer the truth; off by default: it slows
    /// the 200x150 rocket's first fixes, see the README)
    #[arg(long, default_value_t = 0.0)]
    map_view_sigma: f64,
    /// A fix the inertial filter refuses as inconsistent doubts the filter
    /// (its pose and velocity sigmas doubled, the search widened) at once
    /// when its inliers cover at least this many cells of the 8x6 image
    /// grid; a narrower view's (a hole in the cloud) only when it agrees
    /// with the refused fix before it since the last accepted one, both
    /// saying the filter is off by the same (0: every one at once; 49 or
    /// more: every one only so)
    #[arg(long, default_value_t = 24)]
    doubt_min_cells: usize,
    /// A frame whose matches do not agree counts as a miss (four in a row
    /// double the pose's doubt) only when they span at least this many
    /// cells of the 8x6 image grid: a narrower view's (a hole in the cloud)
    /// says little of the pose (0: every such frame counts; 24 recovers the
    /// hole runs that stayed lost, see the README)
    #[arg(long, default_value_t = 24)]
    miss_min_cells: usize,
    /// Camera-IMU time offset the inertial filter estimates: its prior
    /// (ms, 1 sigma; 0: the stamps are trusted).
    #[arg(long, default_value_t = 10.0)]
    time_offset_sigma: f64,
    /// Use frames without a fix only as fixes (the tight filter otherwise
    /// updates with their matches that agree with its prediction, 3 or more).
    #[arg(long)]
    no_prior_gated_update: bool,
    /// Do not update the tight filter with the landmarks found in two
    /// consecutive images (their motion in between: velocity, gyro bias,
    /// time offset).
    #[arg(long)]
    no_track_update: bool,
    /// The sigma each landmark track is weighed with on top of its two
    /// correlation peaks' (px, per coordinate): a floor above the tracks'
    /// scatter (0.1-0.6 px), so the motion they measure does not hold the
    /// pose on its first fixes' errors; lower, they tell the velocity and
    /// the lens more and the position follows the fixes less (see the
    /// README).
    #[arg(long, default_value_t = 2.0)]
    track_sigma: f64,
    /// Do not carry the focal length in the tight filter's state (it is
    /// carried by default, so the motion the accelerometer measures and the
    /// turns the gyro measures, through the landmarks tracked between
    /// images, calibrate it as well as the relief in view; on the 24
    /// realistic runs this learns the lenses and lowers the sum of their
    /// mean errors by a quarter, see the README). Without it each fix's own
    /// evidence calibrates the lens (--no-self-calibration: camera.json's).
    #[arg(long)]
    no_inertial_focal: bool,
    /// Carry the principal point in the tight filter's state (two pixels):
    /// its error tilts the pose every frame sees alike, in the camera's
    /// frame, so a roll about the boresight or the accelerometer's tilt
    /// tells it from an attitude or position error (off by default: it is
    /// then allowed for in each fix's covariance; on the realistic flights
    /// it lowers most mean errors but wanders on the high rocket, see the
    /// README). Not with --estimate-principal-point (each frame's own
    /// evidence).
    #[arg(long, conflicts_with = "estimate_principal_point")]
    inertial_principal_point: bool,
    /// Carry the principal point in the tight filter's state but learn it
    /// from the landmark tracks alone (a roll about the boresight between
    /// two images turns the pixels about the true principal point, and the
    /// database's errors cancel between the images): the fixes count its
    /// uncertainty without moving it, so the database's tilt in a fix is
    /// not taken for the camera's (see the README).
    #[arg(long, conflicts_with_all = ["estimate_principal_point", "inertial_principal_point"])]
    principal_point_from_tracks: bool,
    /// Trust camera.json's focal length instead of estimating it in flight.
    #[arg(long)]
    no_self_calibration: bool,
    /// Focal length error of camera.json (percent, 1 sigma): the
    /// self-calibration's prior.
    #[arg(long, default_value_t = 0.5)]
    focal_sigma: f64,
    /// Principal point error of camera.json (pixels, 1 sigma).
    #[arg(long, default_value_t = 3.0)]
    principal_point_sigma: f64,
    /// Estimate the principal point too (default: kept at camera.json's, its
    /// error allowed for in the focal length's evidence).
    #[arg(long)]
    estimate_principal_point: bool,
    /// Radial distortion k1 error of camera.json (1 sigma): with it, the
    /// self-calibration estimates k1 too; 0 (default) trusts camera.json's.
    #[arg(long, default_value_t = 0.0)]
    k1_sigma: f64,
    /// Height error of the database's landmarks (m, 1 sigma), allowed for in
    /// the focal length's evidence.
    #[arg(long, default_value_t = 20.0)]
    landmark_height_sigma: f64,
    /// Frames whose matches alone give the focal length worse than this
    /// (percent, 1 sigma) do not update it.
    #[arg(long, default_value_t = 0.5)]
    calibration_frame_sigma: f64,
}

#[derive(Clone, Copy, ValueEnum)]
enum FilterArg {
    Tight,
    Loose,
    Fixes,
}

#[derive(Clone, Copy, ValueEnum)]
enum CompressArg {
    Deflate,
    Jpeg,
}

#[derive(clap::Args)]
struct EvaluateArgs {
    /// Flight folder (frames.csv, truth.csv, ...).
    #[arg(long)]
    flight: PathBuf,
    /// Navigator output; several for a comparison table (e.g. 2/4 Hz, with/without gyro).
    #[arg(long = "poses", required = true)]
    poses: Vec<PathBuf>,
    /// Name of each run, in --poses order (default: the poses file's stem); none or one per --poses.
    #[arg(long = "label")]
    labels: Vec<String>,
    /// Per-match residuals, in --poses order (default: matches.csv next to each poses file, if any).
    #[arg(long = "matches")]
    matches: Vec<PathBuf>,
    /// Write trajectory, error, inlier and residual plots (PNG) here; a subfolder per run when several.
    #[arg(long)]
    plot_dir: Option<PathBuf>,
    /// Height of the altitude bands (m).
    #[arg(long, default_value_t = 5000.0)]
    band_m: f64,
    /// Also write the report as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// mimalloc's `mi_option_purge_delay` (position 15 of `mi_option_e` in the
/// mimalloc 2/3 headers that libmimalloc-sys 0.1 bundles).
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

fn main() -> ExitCode {
    // Keep freed memory mapped: builds free and re-allocate megabyte buffers per
    // tile, and handing them back to the kernel cost ~15% in page faults.
    unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1) };
    // No transparent huge pages for this process: the kernel zeroes a whole
    // 2 MB page on its first touch, and on the benchmark machine those fresh
    // huge pages (the pyramid levels, mostly) cost ~12% of a build in
    // clear_page, where 4 KB pages come from the kernel's recently freed ones.
    // (mimalloc's own allow_thp option is read before main runs.)
    #[cfg(target_os = "linux")]
    // SAFETY: prctl with PR_SET_THP_DISABLE only sets a flag of this process.
    unsafe {
        libc::prctl(libc::PR_SET_THP_DISABLE, 1, 0, 0, 0);
    }
    tracing_subscriber::fmt()
        .with_env_filter(EnvFilter::try_from_env("TRN_LOG").unwrap_or_else(|_| EnvFilter::new("info")))
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .init();
    let cli = Cli::try_parse_args(std::env::args_os()).unwrap_or_else(|e| e.exit());
    // A reader that closes the pipe (`trn evaluate ... | head`) ends a
    // command quietly, as other command-line tools do: Rust ignores
    // SIGPIPE, and the next print then panicked. Not the server's: a
    // client's closed socket must not end it.
    #[cfg(unix)]
    if !matches!(cli.command, Command::Serve(_)) {
        // SAFETY: restores one signal's default action, before this process
        // starts a thread of its own.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    let result = match cli.command {
        Command::Build(a) => run_build(a),
        Command::Synth(a) => run_synth(a),
        Command::DegradeDem(a) => run_degrade_dem(a),
        Command::Simulate(a) => run_simulate(a),
        Command::Navigate(a) => run_navigate(a),
        Command::Evaluate(a) => run_evaluate(a),
        Command::Serve(a) => run_serve(a),
        Command::Coverage(a) => run_coverage(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// The builder's options from `trn build`'s (with none given but the inputs:
/// `BuildOptions::new`'s defaults, which a test holds them to).
fn build_options(a: &BuildArgs) -> anyhow::Result<BuildOptions> {
    let mut o = BuildOptions::new(a.orthos.clone(), Vec::new(), a.out.clone());
    o.dem = a.dem.clone().inputs();
    o.ortho_bands = a.ortho_bands.clone();
    o.template_size = a.template_size;
    o.min_template_size = a.min_template_size;
    o.spacing_px = a.spacing;
    o.per_cell = a.per_cell;
    o.fill_share = a.fill_share;
    o.levels = a.levels;
    o.base_gsd_m = a.base_gsd;
    // One-line errors (clap's own "required arguments" message spans lines).
    match (&a.camera, a.altitude, a.max_off_nadir) {
        (Some(_), None, _) => anyhow::bail!("--camera needs --altitude MIN..MAX (metres above the terrain)"),
        (None, Some(_), _) => anyhow::bail!("--altitude needs --camera camera.json"),
        (None, None, Some(_)) => anyhow::bail!("--max-off-nadir needs --camera and --altitude"),
        _ => {}
    }
    if let (Some(camera), Some((lo, hi))) = (&a.camera, a.altitude) {
        let c = trn_flight::read_camera(camera)?.model;
        o.mission = Some(trn_builder::sizing::Mission {
            width_px: c.width,
            height_px: c.height,
            fx: c.fx,
            fy: c.fy,
            altitude_min_m: lo,
            altitude_max_m: hi,
            max_off_nadir_deg: a.max_off_nadir.unwrap_or(0.0),
        });
    }
    o.min_contrast_std = a.min_contrast;
    o.min_shi_tomasi = a.min_shi_tomasi;
    o.search_radius_px = a.search_radius;
    o.max_second_peak = a.max_second_peak;
    o.max_relief_gsd = a.max_relief;
    o.max_hidden_share = a.max_hidden;
    o.suns = a.suns.clone();
    o.max_shading_share = a.max_shading;
    Ok(o)
}

fn run_build(a: BuildArgs) -> anyhow::Result<()> {
    set_threads(a.threads)?;
    let cancel = cancel_flag()?;
    let o = build_options(&a)?;
    // The plan is checked before the build: a bad one leaves nothing at --out.
    let plan = match &a.coverage_plan {
        Some(p) => {
            let text = std::fs::read(p).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
            let req: trn_server::coverage::CoverageRequest = serde_json::from_slice(&text)
                .map_err(|e| anyhow::anyhow!("{}: not a coverage plan: {e}", p.display()))?;
            trn_server::coverage::plan_poses(&req)
                .map_err(|e| anyhow::anyhow!("{}: {}", p.display(), e.message))?;
            Some((p, req))
        }
        None => None,
    };
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{msg} [{bar:40}] {pos}/{len} tiles, {elapsed_precise} (eta {eta})",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let progress = |p: trn_builder::Progress| match p {
        trn_builder::Progress::Group { label, tiles } => {
            bar.reset();
            bar.set_length(tiles);
            bar.set_message(format!("building {label}"));
        }
        trn_builder::Progress::Tile => bar.inc(1),
        trn_builder::Progress::GroupDone => bar.finish_and_clear(),
    };
    let report = trn_builder::build(&o, &cancel, &progress);
    bar.finish_and_clear();
    let report = report?;
    let mut json = serde_json::to_value(&report)?;
    if let Some((p, req)) = plan {
        let db = trn_store::LandmarkDb::open(&report.out)?;
        let levels = trn_view::DbLevel::of(&db.levels()?);
        let cov = trn_server::coverage::coverage_query(&db, &levels, &req)
            .map_err(|e| anyhow::anyhow!("{}: {}", p.display(), e.message))?;
        let mut n: Vec<usize> = cov.points.iter().map(|q| q.landmarks).collect();
        n.sort_unstable();
        tracing::info!(
            "coverage of {}: {} points, landmarks in view min {} / median {}, {} stretch(es) below {}",
            p.display(),
            n.len(),
            cov.min_landmarks,
            n.get(n.len() / 2).copied().unwrap_or(0),
            cov.stretches.len(),
            cov.threshold
        );
        json["coverage"] = serde_json::json!({
            "plan": p,
            "median_landmarks": n.get(n.len() / 2).copied().unwrap_or(0),
            "report": cov,
        });
    }
    println!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

/// `MIN..MAX` metres, e.g. `3000..9000`.
fn parse_altitude(s: &str) -> Result<(f64, f64), String> {
    let (lo, hi) =
        s.split_once("..").ok_or_else(|| format!("{s:?}: expected MIN..MAX metres, e.g. 3000..9000"))?;
    let num =
        |v: &str| v.trim().parse::<f64>().map_err(|_| format!("{s:?}: {v:?} is not a number of metres"));
    let (lo, hi) = (num(lo)?, num(hi)?);
    if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && hi >= lo) {
        return Err(format!("{s:?}: needs 0 < MIN <= MAX"));
    }
    Ok((lo, hi))
}

/// A share in 0..=1.
fn parse_share(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("{s:?}: expected a share in 0..=1")),
    }
}

/// `AZ,EL[,DIFFUSE]` (degrees, share) as a sun.
fn parse_sun(s: &str) -> Result<trn_landmark::lighting::SunLight, String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    if !(2..=3).contains(&parts.len()) {
        return Err(format!("{s:?}: expected AZ,EL[,DIFFUSE], e.g. 250,25"));
    }
    let num =
        |v: &str, what: &str| v.parse::<f64>().map_err(|_| format!("{s:?}: {v:?} is not a number ({what})"));
    let sun = trn_landmark::lighting::SunLight {
        azimuth_deg: num(parts[0], "azimuth, degrees")?,
        elevation_deg: num(parts[1], "elevation, degrees")?,
        ambient: parts.get(2).map(|v| num(v, "diffuse share")).transpose()?.unwrap_or(0.25),
    };
    if !(sun.azimuth_deg.is_finite() && (-360.0..=360.0).contains(&sun.azimuth_deg)) {
        return Err(format!("{s:?}: azimuth must be -360..=360 degrees"));
    }
    if !(sun.elevation_deg > 0.0 && sun.elevation_deg <= 90.0) {
        return Err(format!("{s:?}: elevation must be in (0, 90] degrees"));
    }
    if !(0.0..=1.0).contains(&sun.ambient) {
        return Err(format!("{s:?}: the diffuse share must be in 0..=1"));
    }
    Ok(sun)
}

/// Sizes rayon's pool when `--threads` is given (default: all cores).
fn set_threads(threads: Option<u32>) -> anyhow::Result<()> {
    if let Some(n) = threads {
        rayon::ThreadPoolBuilder::new().num_threads(n as usize).build_global()?;
    }
    Ok(())
}

/// Ctrl-C sets the flag; long jobs stop at the next safe point and clean up
/// (the output is never half-written).
fn cancel_flag() -> anyhow::Result<Arc<AtomicBool>> {
    let cancel = Arc::new(AtomicBool::new(false));
    let flag = cancel.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::Relaxed))?;
    Ok(cancel)
}

fn run_simulate(a: SimulateArgs) -> anyhow::Result<()> {
    set_threads(a.threads)?;
    let cancel = cancel_flag()?;
    let opts = trn_sim::SimOptions {
        sources: trn_sim::SceneSources { ortho: a.ortho, ortho_bands: a.ortho_bands, dem: a.dem.inputs() },
        scenario: a.scenario,
        out: a.out,
        max_duration_s: a.duration,
    };
    let report = trn_sim::simulate(&opts, &cancel)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

/// The navigator's settings from `trn navigate`'s options (with none given:
/// `NavParams::default()`, which a test holds them to).
fn nav_params(a: &NavigateArgs) -> trn_navigator::NavParams {
    let mut params = trn_navigator::NavParams { use_gyro: !a.no_gyro, ..Default::default() };
    params.alpha_max_deg = a.alpha_max;
    params.min_inliers = a.min_inliers;
    params.ransac_threshold_px = a.ransac_threshold;
    params.min_inlier_share = a.min_inlier_share;
    params.max_height_jump_m = a.max_height_jump;
    params.max_landmarks = a.max_landmarks;
    params.threads = a.threads as usize;
    params.acquisition_budget_g = a.acquisition_budget;
    params.init_sigma_m = a.init_sigma_m;
    params.init_sigma_deg = a.init_sigma_deg;
    params.filter = match a.filter {
        FilterArg::Tight => trn_navigator::FilterMode::Tight,
        FilterArg::Loose => trn_navigator::FilterMode::Loose,
        FilterArg::Fixes => trn_navigator::FilterMode::Fixes,
    };
    params.init_velocity_sigma_m_s = a.init_velocity_sigma;
    params.accel_bias_m_s2 = a.accel_bias;
    params.map_sigma_m = a.map_sigma;
    params.map_tau_s = a.map_tau;
    params.map_att_sigma_deg = a.map_att_sigma;
    params.map_view_sigma_px = a.map_view_sigma;
    params.doubt_min_cells = a.doubt_min_cells;
    params.miss_min_cells = a.miss_min_cells;
    params.time_offset_sigma_s = a.time_offset_sigma / 1e3;
    params.prior_gated_update = !a.no_prior_gated_update;
    params.track_update = !a.no_track_update;
    params.track.sigma_px = a.track_sigma;
    params.inertial_focal = !a.no_inertial_focal;
    params.inertial_principal_point = a.inertial_principal_point;
    params.principal_point_from_tracks = a.principal_point_from_tracks;
    params.sun = a.sun;
    params.shading_weight = a.shading_weight;
    params.duplicate_separation = a.duplicate_separation;
    params.gyro_arw_deg_sqrt_s = a.gyro_arw / 60.0;
    params.gyro_bias_deg_s = a.gyro_bias / 3600.0;
    params.gyro_max_jump_deg_s = a.gyro_max_jump;
    params.imu_gap_doubt_deg_s_sqrt_s = a.imu_gap_doubt;
    params.accel_max_jump_m_s2 = a.accel_max_jump;
    params.gyro_range_deg_s = a.gyro_range;
    params.accel_range_m_s2 = a.accel_range;
    params.calibration = (!a.no_self_calibration).then(|| trn_navigator::calibration::CalibrationParams {
        focal_sigma_rel: a.focal_sigma / 100.0,
        principal_sigma_px: a.principal_point_sigma,
        principal_point: a.estimate_principal_point,
        k1_sigma: a.k1_sigma,
        landmark_height_sigma_m: a.landmark_height_sigma,
        max_frame_sigma_rel: a.calibration_frame_sigma / 100.0,
        ..Default::default()
    });
    params
}

fn run_navigate(a: NavigateArgs) -> anyhow::Result<()> {
    let opts = trn_navigator::RunOptions {
        rate_hz: a.rate,
        params: nav_params(&a),
        matches_dir: a.matches_dir.clone(),
        imu_rate: a.imu_rate,
    };
    // Every option is checked before any file is opened or written.
    opts.check()?;
    if let Some(dir) = &a.matches_dir {
        std::fs::create_dir_all(dir)
            .map_err(|e| anyhow::anyhow!("invalid option --matches-dir {}: {e}", dir.display()))?;
    }
    let flight = trn_flight::Flight::open(&a.flight)?;
    let source: Box<dyn trn_navigator::LandmarkSource> = match (&a.db, &a.server) {
        (Some(db), _) => Box::new(trn_navigator::DbSource::open(db)?),
        (None, Some(url)) => Box::new(trn_client::HttpSource::connect(url)?),
        (None, None) => anyhow::bail!("give --db or --server"),
    };
    let bar = indicatif::ProgressBar::new(flight.frames.len() as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "navigate [{bar:40}] {pos}/{len} frames, {elapsed_precise} (eta {eta})",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let run = trn_navigator::run_flight(&flight, source.as_ref(), &opts, |i| bar.set_position(i as u64))?;
    bar.finish_and_clear();
    trn_flight::write_nav_records(&a.out, &run.records)?;
    let matches_path = a.out.with_file_name("matches.csv");
    trn_flight::write_match_records(&matches_path, &run.matches)?;
    let cov_path = a.out.with_file_name("covariance.csv");
    trn_flight::write_pose_covariances(&cov_path, &run.covariances)?;
    if a.imu_rate {
        let (records, covariances): (Vec<_>, Vec<_>) = run.imu_rate.into_iter().unzip();
        let (poses_imu, cov_imu) =
            (a.out.with_file_name("poses-imu.csv"), a.out.with_file_name("covariance-imu.csv"));
        trn_flight::write_nav_records(&poses_imu, &records)?;
        trn_flight::write_pose_covariances(&cov_imu, &covariances)?;
        tracing::info!(
            "IMU rate: {} poses in {} and {}",
            records.len(),
            poses_imu.display(),
            cov_imu.display()
        );
    }
    let report = run.report;
    tracing::info!(
        "{} of {} frames processed, {} fixes ({} rejected for too few inliers, {} for too small a share of inliers, {} acquisitions for too few of the templates searched for, {} for inliers on a line or in a cluster, {} for their height, {} as inconsistent with the inertial filter ({} of a narrow view, not doubting it), {} acquisitions held for the next frame to confirm; {} frames without a fix updated the filter with their matches; {} frames updated it with the landmarks tracked from the image before; {} frames without a fix, in a run of them, doubted its pose), median {:.1} ms per frame; wrote {}, {} and {}",
        report.processed,
        report.frames,
        report.fixes,
        report.rejected.few_inliers,
        report.rejected.inlier_share,
        report.rejected.found_share,
        report.rejected.spread,
        report.rejected.height,
        report.rejected.inconsistent,
        report.narrow_inconsistent,
        report.rejected.unconfirmed,
        report.prior_gated_updates,
        report.track_updates,
        report.doubted_frames,
        report.median_ms,
        a.out.display(),
        matches_path.display(),
        cov_path.display()
    );
    if report.gyro_jumps > 0 {
        tracing::warn!(
            "{} gyro rate jump(s) beyond {} deg/s from one sample to the next: the angle each turned was doubted (--gyro-max-jump)",
            report.gyro_jumps,
            a.gyro_max_jump
        );
    }
    if report.gyro_jumps_undone > 0 {
        tracing::warn!(
            "{} frame(s) found their landmarks with the gyro's jumps since the fix before undone: the image saw the camera where it was before them (a glitch, not a turn)",
            report.gyro_jumps_undone
        );
    }
    if report.map_doubts > 0 {
        tracing::warn!(
            "{} fix(es) found the map offset beyond its prior: the images were being explained by a database error, most likely a velocity gone wrong; each restarted it and doubted the pose",
            report.map_doubts
        );
    }
    if report.accel_jumps > 0 {
        tracing::warn!(
            "{} accelerometer jump(s) beyond {} m/s^2 from one sample to the next: the velocity each added was doubted (--accel-max-jump)",
            report.accel_jumps,
            a.accel_max_jump
        );
    }
    if let Some(first) = report.skipped_images.first() {
        tracing::warn!(
            "{} of {} frames had no usable image (the first at t {:.3} s: {}: {}); their poses were carried (status propagated), and the report lists them",
            report.skipped_images.len(),
            report.frames,
            first.t,
            first.image.display(),
            first.reason
        );
    }
    if let Some(o) = &report.time_offset {
        tracing::info!("camera-IMU time offset: {:+.2} ms +- {:.2} ms", o.offset_ms, o.sigma_ms);
    }
    if let Some(g) = &report.gyro_bias_imu_deg_h {
        tracing::info!(
            "gyro bias (IMU x, y, z): {:+.2} {:+.2} {:+.2} deg/h +- {:.2} {:.2} {:.2}",
            g.x,
            g.y,
            g.z,
            g.sigma_x,
            g.sigma_y,
            g.sigma_z
        );
    }
    if let Some(c) = &report.calibration {
        tracing::info!(
            "self-calibration: focal length {:+.3}% +- {:.3}% of camera.json's, k1 {:+.5} +- {:.5} ({} fixes used, {} too weak, {} refused)",
            c.focal_rel * 100.0,
            c.focal_sigma_rel * 100.0,
            c.k1,
            c.k1_sigma,
            c.frames_used,
            c.frames_weak,
            c.frames_refused
        );
    }
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

fn run_degrade_dem(a: DegradeDemArgs) -> anyhow::Result<()> {
    let report = trn_sim::dem_variant::degrade_dem(&trn_sim::dem_variant::DemVariantOptions {
        dem: a.dem,
        out: a.out,
        cell_m: a.cell_m,
        noise_rms_m: a.noise_m,
        noise_scale_m: a.noise_scale_m,
        seed: a.seed,
    })?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

fn run_synth(a: SynthArgs) -> anyhow::Result<()> {
    let scene = trn_raster::synth::SynthScene {
        size: a.size,
        gsd_m: a.gsd,
        east_m: a.east,
        north_m: a.north,
        seed: a.seed,
        relief_m: a.relief,
        nodata_border: a.nodata_border,
        compression: match a.compress {
            CompressArg::Deflate => trn_raster::synth::Compression::Deflate,
            CompressArg::Jpeg => trn_raster::synth::Compression::Jpeg,
        },
    };
    scene.write(&a.ortho, &a.dem)?;
    println!("wrote {} and {}", a.ortho.display(), a.dem.display());
    Ok(())
}

fn run_evaluate(a: EvaluateArgs) -> anyhow::Result<()> {
    let n = a.poses.len();
    if !a.labels.is_empty() && a.labels.len() != n {
        anyhow::bail!("--label given {} times for {n} --poses: give none or one per --poses", a.labels.len());
    }
    if !a.matches.is_empty() && a.matches.len() != n {
        anyhow::bail!(
            "--matches given {} times for {n} --poses: give none or one per --poses",
            a.matches.len()
        );
    }
    let runs: Vec<trn_eval::RunInput> = a
        .poses
        .into_iter()
        .enumerate()
        .map(|(i, p)| {
            let mut r = trn_eval::RunInput::new(p);
            if let Some(l) = a.labels.get(i) {
                r.label = l.clone();
            }
            r.matches = a.matches.get(i).cloned();
            r
        })
        .collect();
    let opts = trn_eval::Options { band_m: a.band_m, plot_dir: a.plot_dir };
    let report = trn_eval::evaluate(&a.flight, &runs, &opts)?;
    print!("{report}");
    if let Some(path) = &a.json {
        trn_eval::write_json(path, &report)?;
    }
    Ok(())
}

#[derive(clap::Args)]
struct ServeArgs {
    /// Landmark database (from trn build); opened read-only, reopened on SIGHUP.
    #[arg(long)]
    db: PathBuf,
    /// Address to listen on (port 0: any free port; the bound address is printed).
    #[arg(long, default_value = "127.0.0.1:8080")]
    listen: String,
    /// Read-only database connections (queries at once; default: 2 per core, at least 4).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
    connections: Option<u32>,
    /// Requests handled at once; more wait their turn.
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    max_concurrency: u32,
    /// Requests taking longer are answered 408 (seconds).
    #[arg(long, default_value_t = 30.0)]
    timeout_s: f64,
    /// Largest request body (bytes); larger ones are answered 413.
    #[arg(long, default_value_t = 2 << 20)]
    max_body_bytes: usize,
    /// Also reload when the file at --db changes (checked every second).
    #[arg(long)]
    watch: bool,
    /// Worker threads (default: all cores).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
    /// Serve from memory when the whole database (encoded templates and index)
    /// fits in this many MB; a larger one is queried in SQLite. 0: never.
    #[arg(long, default_value_t = trn_server::DEFAULT_CACHE_MB,
          value_parser = clap::value_parser!(u64).range(0..=1 << 24))]
    cache_mb: u64,
}

#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("source").required(true).args(["db", "server"])))]
struct CoverageArgs {
    /// Landmark database (from trn build); the report is computed here.
    #[arg(long)]
    db: Option<PathBuf>,
    /// Landmark server (trn serve) instead of --db, e.g. http://127.0.0.1:8080: the server
    /// computes the report (POST /v1/coverage) and lists the footprints for --png.
    #[arg(long, value_name = "URL")]
    server: Option<String>,
    /// Planned trajectory: the JSON body of POST /v1/coverage (camera, poses or waypoints + attitude).
    #[arg(long)]
    plan: PathBuf,
    /// Also write the report as GeoJSON.
    #[arg(long)]
    geojson: Option<PathBuf>,
    /// Also draw the trajectory over the landmark footprints (PNG).
    #[arg(long)]
    png: Option<PathBuf>,
    /// Width of the PNG map (px).
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u32).range(16..=16384))]
    png_width: u32,
}

fn run_serve(a: ServeArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        a.timeout_s.is_finite() && a.timeout_s > 0.0,
        "invalid option --timeout-s: must be a number of seconds > 0"
    );
    let mut o = trn_server::ServeOptions::new(a.db, a.listen);
    if let Some(n) = a.connections {
        o.connections = n as usize;
    }
    o.max_concurrency = a.max_concurrency as usize;
    o.request_timeout = std::time::Duration::from_secs_f64(a.timeout_s);
    o.max_body_bytes = a.max_body_bytes;
    o.watch = a.watch;
    o.threads = a.threads.map(|n| n as usize);
    o.cache_bytes = a.cache_mb << 20;
    trn_server::serve(o, |addr| {
        use std::io::Write;
        // Scripts and tests read the bound address from this line.
        println!("listening on http://{addr}");
        let _ = std::io::stdout().flush();
    })?;
    Ok(())
}

fn run_coverage(a: CoverageArgs) -> anyhow::Result<()> {
    use trn_server::coverage_cli::CoverageSource;
    let source = match (&a.db, &a.server) {
        (Some(db), None) => CoverageSource::Db(db),
        (None, Some(url)) => CoverageSource::Server(url),
        _ => anyhow::bail!("give either --db or --server"),
    };
    let report = trn_server::coverage_cli::run_cli(
        source,
        &a.plan,
        a.geojson.as_deref(),
        a.png.as_deref().map(|p| (p, a.png_width)),
    )?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each field of two `{:?}` renderings of one struct alike.
    fn assert_same_fields(from_cli: &str, library: &str) {
        let differing: Vec<_> = from_cli
            .split(", ")
            .zip(library.split(", "))
            .filter(|(c, l)| c != l)
            .map(|(c, l)| format!("cli {c} / library {l}"))
            .collect();
        assert!(differing.is_empty(), "defaults differ: {differing:#?}");
    }

    /// `trn navigate`'s option defaults are the navigator's own: one value
    /// each, whichever side a change moves.
    #[test]
    fn navigate_defaults_are_the_navigators() {
        let cli =
            Cli::try_parse_args(["trn", "navigate", "--db", "l.gpkg", "--flight", "f", "--out", "p.csv"])
                .expect("minimal navigate arguments parse");
        let Command::Navigate(a) = cli.command else { panic!("not navigate") };
        let from_cli = format!("{:?}", nav_params(&a));
        let library = format!("{:?}", trn_navigator::NavParams::default());
        assert_same_fields(&from_cli, &library);
    }

    /// A negative number after an option is its value: refused by the
    /// option's own parser (naming the option) where it cannot be negative,
    /// taken where it can.
    #[test]
    fn a_negative_number_is_the_options_value() {
        let args = ["trn", "navigate", "--db", "l.gpkg", "--flight", "f", "--out", "p.csv"];
        for (option, value) in [("--miss-min-cells", "-1"), ("--min-inliers", "-3"), ("--threads", "-2")] {
            let err = Cli::try_parse_args(args.into_iter().chain([option, value]))
                .err()
                .unwrap_or_else(|| panic!("{option} {value} parsed"));
            assert_eq!(err.kind(), clap::error::ErrorKind::ValueValidation, "{option} {value}: {err}");
            let message = err.to_string();
            assert!(message.contains(option) && message.contains(value), "{option} {value}: {message}");
        }
        let cli = Cli::try_parse_args([
            "trn", "synth", "--ortho", "o.tif", "--dem", "d.tif", "--east", "-500", "--north", "-250.5",
        ])
        .expect("negative offsets parse");
        let Command::Synth(a) = cli.command else { panic!("not synth") };
        assert_eq!((a.east, a.north), (-500.0, -250.5));
        // A flag is still a flag: `-h` is not taken for a value.
        let err = Cli::try_parse_args(args.into_iter().chain(["--min-inliers", "-h"])).err().expect("-h");
        assert_ne!(err.kind(), clap::error::ErrorKind::ValueValidation);
    }

    /// `trn build`'s option defaults are the builder's own, likewise.
    #[test]
    fn build_defaults_are_the_builders() {
        let cli =
            Cli::try_parse_args(["trn", "build", "--ortho", "o.tif", "--dem", "d.tif", "--out", "l.gpkg"])
                .expect("minimal build arguments parse");
        let Command::Build(a) = cli.command else { panic!("not build") };
        let library = BuildOptions::new(vec!["o.tif".into()], vec!["d.tif".into()], "l.gpkg".into());
        let from_cli = format!("{:?}", build_options(&a).expect("options"));
        let library = format!("{library:?}");
        assert_same_fields(&from_cli, &library);
    }
}

//! The offline landmark builder: cuts orthoimagery and elevation models into
//! small north-up image templates, 3D-referenced on the WGS84 ellipsoid, and
//! stores them in a landmark database (SQLite/GeoPackage, see `trn-store`).
//!
//! The main entry point is [`build`] with its [`BuildOptions`]. Per ortho mosaic
//! it walks a luminance pyramid level by level in tiles (memory bounded, in
//! parallel), scores texture and distinctiveness ([`select`]), cuts the chosen
//! templates on the local tangent plane with the DEM's terrain ([`extract`]), and
//! writes the database to a temporary file that is renamed into place only when
//! everything succeeded. The rasters are read through `trn-raster` (the one
//! owner of GDAL); the tile worker is in `group.rs`.
//!
//! ```
//! use std::path::PathBuf;
//! use std::sync::atomic::AtomicBool;
//! use trn_builder::{build, BuildOptions};
//!
//! // Bad input stops the build before any work, with a message naming the file,
//! // and leaves nothing at --out.
//! let out = std::env::temp_dir().join(format!("trn-doc-{}.gpkg", std::process::id()));
//! let opts = BuildOptions::new(vec![PathBuf::from("no-such-ortho.tif")], vec![PathBuf::from("dem.tif")], out.clone());
//! let err = build(&opts, &AtomicBool::new(false), &|_| {}).unwrap_err();
//! assert!(err.to_string().contains("no-such-ortho.tif"), "{err}");
//! assert!(!out.exists());
//! ```

pub mod error;
pub mod extract;
mod group;
pub mod lighting;
pub mod pyramid;
pub mod select;
pub mod sizing;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde::Serialize;
use tracing::{info, warn};
use trn_landmark::lighting::SunLight;
use trn_landmark::{GeoBox, Template};

pub use error::{BuildError, Result};
use extract::Reject;
use lighting::SunGrid;
use select::CellStats;
use sizing::{GsdRange, LevelSpec, Mission};
use source::{Luminance, RasterInfo};
use terrain::DemSpec;
pub use trn_raster::{open_dem_specs, source, terrain, DemInputs, DemVertical, RasterError, EGM96_GRID};

#[derive(Clone, Debug, Serialize)]
pub struct BuildOptions {
    pub orthos: Vec<PathBuf>,
    #[serde(flatten)]
    pub dem: DemInputs,
    pub out: PathBuf,
    /// 1-based bands making the luminance: one (grey) or three (red, green, blue).
    pub ortho_bands: Option<Vec<usize>>,
    /// Largest template side (pixels): coarse levels' templates.
    pub template_size: u32,
    /// Smallest template side (pixels): the finest level holds templates of
    /// half `template_size` at the ortho's resolution when they are at least
    /// this big (see [`sizing::ladder`]).
    pub min_template_size: u32,
    /// Side of the cell that gets `per_cell` landmarks, in the level's
    /// template pixels; `None`: the level's template size times its share
    /// from [`sizing::spacing_shares`] (one template footprint without a
    /// mission; with one, what gives its camera enough landmarks in view).
    pub spacing_px: Option<u32>,
    pub per_cell: usize,
    /// Density fill (`--fill-share`): where fewer than this share of the
    /// cells a camera sees around a cell kept a landmark (water, bare ground,
    /// the scene's edge), its textured cells keep up to 4 times `per_cell`
    /// ([`select::Fill`]); 0: off; `None`: [`sizing::USABLE_SHARE`] for a
    /// mission (its cells are sized for it) and, without one, on a finest
    /// level whose ortho is too coarse for the envelope's finest cameras;
    /// off on the default envelope's other levels (whose cameras see several
    /// times the landmarks they need): [`sizing::fill_windows`].
    pub fill_share: Option<f32>,
    /// Number of levels; `None`: as many as the served camera resolutions need.
    pub levels: Option<u8>,
    /// GSD of the finest pyramid step; `None`: the coarsest ortho's pixel size.
    pub base_gsd_m: Option<f64>,
    /// The mission the database is sized for; `None`: the default envelope
    /// ([`sizing::DEFAULT_ENVELOPE`]).
    pub mission: Option<Mission>,
    pub min_contrast_std: f32,
    pub min_shi_tomasi: f32,
    pub max_saturated: f32,
    /// Uniqueness search radius (template pixels) and highest allowed second NCC peak.
    pub search_radius_px: u32,
    pub max_second_peak: f32,
    /// Largest RMS terrain distance from the template's plane, in GSDs;
    /// `None` (default): relief is modelled by the height grid.
    pub max_relief_gsd: Option<f64>,
    /// Largest share of a template its own relief may hide at the served
    /// view angles.
    pub max_hidden_share: f64,
    pub height_grid_n: u32,
    /// Suns to bake into the templates (`--sun`): each landmark is stored
    /// once per sun, rendered under it ([`lighting`]); empty: the ortho as
    /// imaged.
    pub suns: Vec<SunLight>,
    /// Largest shading share a template may have (`--max-shading`): above
    /// it, the cell takes its next candidate; `None`: no limit.
    pub max_shading_share: Option<f64>,
}

/// Most a cell's quota grows under the density fill ([`BuildOptions::fill_share`]).
pub const FILL_MAX_BOOST: usize = 4;

/// View angle from the vertical up to which a database built without a
/// mission keeps landmarks visible (self-occlusion test).
pub const DEFAULT_MAX_VIEW_DEG: f64 = 60.0;

impl BuildOptions {
    pub fn new(orthos: Vec<PathBuf>, dems: Vec<PathBuf>, out: PathBuf) -> Self {
        Self {
            orthos,
            dem: DemInputs::new(dems),
            out,
            ortho_bands: None,
            template_size: 32,
            min_template_size: 12,
            spacing_px: None,
            per_cell: 1,
            fill_share: None,
            levels: None,
            base_gsd_m: None,
            mission: None,
            min_contrast_std: 4.0,
            min_shi_tomasi: 1.0,
            max_saturated: 0.1,
            search_radius_px: 8,
            max_second_peak: 0.9,
            max_relief_gsd: None,
            max_hidden_share: 0.5,
            height_grid_n: 9,
            suns: Vec::new(),
            max_shading_share: None,
        }
    }

    /// Cell side (template pixels) of a level of `size_px` templates whose
    /// default cell is `share` of its footprint ([`sizing::spacing_shares`]).
    pub fn spacing(&self, size_px: u32, share: f64) -> u32 {
        self.spacing_px.unwrap_or(((size_px as f64 * share).round() as u32).max(1))
    }

    /// The density fill's window and share per level of `specs`
    /// ([`sizing::fill_windows`]; a share of 0: no fill).
    pub fn fill_windows(&self, specs: &[LevelSpec]) -> Vec<sizing::FillWindow> {
        sizing::fill_windows(specs, &self.gsd_range(), self.mission.as_ref(), self.fill_share.map(f64::from))
    }

    /// Camera resolutions the database is sized for.
    pub fn gsd_range(&self) -> GsdRange {
        match &self.mission {
            Some(m) => m.gsd_range(),
            None => GsdRange::of_envelope(&sizing::DEFAULT_ENVELOPE),
        }
    }

    /// Largest view angle from the vertical the database serves.
    pub fn max_view_deg(&self) -> f64 {
        self.mission.as_ref().map_or(DEFAULT_MAX_VIEW_DEG, Mission::max_view_deg)
    }

    /// The level ladder over a finest pyramid step of `base_gsd_m`.
    pub fn ladder(&self, base_gsd_m: f64) -> Vec<LevelSpec> {
        sizing::ladder(base_gsd_m, self.min_template_size, self.template_size, &self.gsd_range(), self.levels)
    }

    fn check(&self) -> Result<()> {
        let bad = |option, reason: &str| Err(BuildError::Option { option, reason: reason.into() });
        if self.orthos.is_empty() {
            return bad("--ortho", "give at least one orthoimage");
        }
        if self.dem.files.is_empty() {
            return bad("--dem", "give at least one DEM");
        }
        if !(8..=512).contains(&self.template_size) {
            return bad("--template-size", "must be 8..=512 pixels");
        }
        if !(8..=self.template_size).contains(&self.min_template_size) {
            return bad("--min-template-size", "must be 8 pixels up to --template-size");
        }
        if self.spacing_px.is_some_and(|s| s < self.template_size / 2) {
            return bad("--spacing", "must be at least half the template size");
        }
        if self.per_cell == 0 {
            return bad("--per-cell", "must be at least 1");
        }
        if self.fill_share.is_some_and(|f| !(f.is_finite() && (0.0..=1.0).contains(&f))) {
            return bad("--fill-share", "must be a share in 0..=1");
        }
        if matches!(self.levels, Some(0) | Some(13..)) {
            return bad("--levels", "must be 1..=12");
        }
        if let Some(g) = self.base_gsd_m {
            if !(g.is_finite() && g > 0.0) {
                return bad("--base-gsd", "must be a positive number of metres");
            }
        }
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if self.max_relief_gsd.is_some_and(|v| !positive(v)) {
            return bad("--max-relief", "must be a positive number of GSDs");
        }
        if !(self.max_hidden_share.is_finite() && (0.0..=1.0).contains(&self.max_hidden_share)) {
            return bad("--max-hidden", "must be a share in 0..=1");
        }
        if let Some(m) = &self.mission {
            if !(m.altitude_min_m.is_finite()
                && m.altitude_min_m > 0.0
                && m.altitude_max_m >= m.altitude_min_m)
            {
                return bad("--altitude", "must be MIN..MAX metres above the terrain, 0 < MIN <= MAX");
            }
            if !(m.max_off_nadir_deg.is_finite() && (0.0..90.0).contains(&m.max_off_nadir_deg)) {
                return bad("--max-off-nadir", "must be 0..90 degrees");
            }
            if !(positive(m.fx) && positive(m.fy) && m.width_px > 0 && m.height_px > 0) {
                return bad("--camera", "needs a positive size and focal length");
            }
        }
        if !(self.min_contrast_std.is_finite() && self.min_contrast_std >= 0.0) {
            return bad("--min-contrast", "must be a number >= 0");
        }
        if !(self.min_shi_tomasi.is_finite() && self.min_shi_tomasi >= 0.0) {
            return bad("--min-shi-tomasi", "must be a number >= 0");
        }
        if self.search_radius_px == 0 {
            return bad("--search-radius", "must be at least 1 pixel");
        }
        if !(self.max_second_peak > 0.0 && self.max_second_peak <= 1.0) {
            return bad("--max-second-peak", "must be in (0, 1]");
        }
        if self.dem.vertical == Some(DemVertical::Geoid) && self.dem.geoid.is_none() {
            return bad("--dem-vertical", "geoid needs --geoid GRID");
        }
        if self.max_shading_share.is_some_and(|v| !(v.is_finite() && (0.0..=1.0).contains(&v))) {
            return bad("--max-shading", "must be a share in 0..=1");
        }
        if self.suns.len() > 255 {
            return bad("--sun", "at most 255 suns");
        }
        for s in &self.suns {
            if !(s.azimuth_deg.is_finite() && (-360.0..=360.0).contains(&s.azimuth_deg)) {
                return bad("--sun", "azimuth must be -360..=360 degrees clockwise from north");
            }
            if !(s.elevation_deg.is_finite() && s.elevation_deg > 0.0 && s.elevation_deg <= 90.0) {
                return bad("--sun", "elevation must be in (0, 90] degrees above the horizon");
            }
            if !(s.ambient.is_finite() && (0.0..=1.0).contains(&s.ambient)) {
                return bad("--sun", "the diffuse share must be in 0..=1");
            }
        }
        if self.out.is_dir() {
            return bad("--out", "is a directory");
        }
        Ok(())
    }
}

/// What a build produced.
#[derive(Clone, Debug, Serialize)]
pub struct BuildReport {
    pub out: PathBuf,
    pub templates: usize,
    pub levels: Vec<LevelReport>,
    /// Camera resolutions (m per image pixel) the database was sized for,
    /// and those at which some level spans 12-48 image pixels.
    pub sized_for_gsd_m: GsdRange,
    pub serves_gsd_m: Option<GsdRange>,
    pub mission: Option<Mission>,
    /// View angle from the vertical of the self-occlusion test.
    pub max_view_deg: f64,
    /// Suns baked into the templates (lighting k is the k-th, from 1).
    pub suns: Vec<SunLight>,
    /// Candidates that passed texture and uniqueness and were offered to extraction.
    pub candidates: usize,
    /// Extraction rejections by reason, all levels.
    pub rejected: BTreeMap<String, usize>,
    pub seconds: f64,
}

/// One level of a build.
#[derive(Clone, Debug, Serialize)]
pub struct LevelReport {
    pub level: u8,
    pub gsd_m: f64,
    pub template_px: u32,
    pub footprint_m: f64,
    /// Side of the selection cell that keeps one landmark (m).
    pub cell_m: f64,
    /// The density fill's share of cells the level aims to give a landmark
    /// ([`sizing::fill_windows`]); 0: no fill.
    pub fill_share: f64,
    pub templates: usize,
    /// Ortho area with usable pixels (selection cells with a valid,
    /// unsaturated window), km², and landmarks per km² of it.
    pub covered_km2: f64,
    pub per_km2: f64,
    /// Camera resolutions at which the level's templates span 12-48 pixels.
    pub serves_gsd_m: GsdRange,
    /// Covered cells left without a landmark, by reason: `no_texture`,
    /// `not_unique`, `refused` (every unique candidate rejected at extraction).
    pub empty_cells: BTreeMap<String, usize>,
    /// Extraction rejections by reason (a cell may still have taken its next candidate).
    pub rejected: BTreeMap<String, usize>,
    /// Mean shading share of the level's landmarks (`TemplateQuality::shading_share`).
    pub mean_shading_share: f64,
}

/// Per level of one ortho group: cells, rejections, area.
#[derive(Clone, Debug, Default)]
struct LevelTally {
    cells: CellStats,
    cell_area_m2: f64,
    covered_m2: f64,
    rejected: HashMap<Reject, usize>,
    /// Sum of the landmarks' shading shares.
    shading_sum: f64,
}

impl LevelTally {
    fn add(&mut self, cells: CellStats, rejected: HashMap<Reject, usize>, shading_sum: f64) {
        self.shading_sum += shading_sum;
        self.covered_m2 += cells.covered as f64 * self.cell_area_m2;
        self.cells += cells;
        for (k, v) in rejected {
            *self.rejected.entry(k).or_default() += v;
        }
    }

    fn merge(&mut self, o: &LevelTally) {
        if self.cell_area_m2 == 0.0 {
            self.cell_area_m2 = o.cell_area_m2;
        }
        self.covered_m2 += o.covered_m2;
        self.shading_sum += o.shading_sum;
        self.cells += o.cells;
        for (k, v) in &o.rejected {
            *self.rejected.entry(*k).or_default() += v;
        }
    }
}

/// An ortho mosaic read as one raster: files with one CRS and pixel size, and
/// files with the same bands in other CRSs or pixel sizes warped onto their grid.
struct OrthoGroup {
    index: u32,
    /// The raster read (the file itself, or a VRT over several).
    path: PathBuf,
    info: RasterInfo,
    lum: Luminance,
    files: Vec<PathBuf>,
}

/// Where a build stands, for a progress display (the CLI draws a bar).
#[derive(Clone, Copy, Debug)]
pub enum Progress<'a> {
    /// An ortho group starts: its first file (and how many more), and its
    /// tiles over all pyramid levels.
    Group { label: &'a str, tiles: u64 },
    /// One more tile of the group is done (from any worker thread).
    Tile,
    /// The group is done.
    GroupDone,
}

/// Builds the landmark database. `cancel` stops the build between tiles; the
/// output is then left untouched. `progress` hears of every group and tile
/// (`&|_| {}` to ignore it).
pub fn build(
    opts: &BuildOptions,
    cancel: &AtomicBool,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<BuildReport> {
    let started = Instant::now();
    opts.check()?;
    let out_dir = out_dir_of(opts)?;
    let Inputs { orthos: ortho_infos, dems } = open_inputs(opts)?;

    let work = tempfile::Builder::new()
        .prefix(".trn-build-")
        .tempdir_in(&out_dir)
        .map_err(|source| BuildError::Io { path: out_dir.clone(), source })?;
    let groups = group_orthos(ortho_infos, work.path())?;
    let dems = trn_raster::dem::mosaic_dems(dems, work.path())?;

    let base_gsd = base_gsd_of(opts, &groups)?;
    let suns = render_suns(opts, &groups, &dems)?;
    let specs = opts.ladder(base_gsd);
    let (range, serves) = (opts.gsd_range(), sizing::served(&specs));
    log_ladder(&specs, &range, serves.as_ref(), base_gsd);

    // The database is written to a temporary file next to the output by its own
    // thread while tiles are processed, and renamed into place only on success.
    let tmp_db = work.path().join("landmarks.gpkg");
    let mut writer = trn_store::DbWriter::create(&tmp_db)?;
    for (k, v) in metadata(opts, &groups, &dems, base_gsd, &specs) {
        writer.set_metadata(&k, &v)?;
    }
    let ctx = BuildCtx {
        opts,
        dems: &dems,
        suns: &suns,
        base_gsd,
        specs: &specs,
        work: work.path(),
        cancel,
        progress,
    };
    let (tallies, summary) = select_and_write(&ctx, &groups, writer)?;
    tracing::debug!("selection and writing done at {:.2} s", started.elapsed().as_secs_f64());
    let (per_level, rejected, candidates) =
        level_reports(&specs, &opts.fill_windows(&specs), &tallies, &summary);
    if summary.template_count == 0 {
        return Err(BuildError::NoTemplates);
    }
    std::fs::rename(&tmp_db, &opts.out)
        .map_err(|source| BuildError::Io { path: opts.out.clone(), source })?;

    let report = BuildReport {
        out: opts.out.clone(),
        templates: summary.template_count as usize,
        levels: per_level,
        sized_for_gsd_m: range,
        serves_gsd_m: serves,
        mission: opts.mission,
        max_view_deg: opts.max_view_deg(),
        suns: opts.suns.clone(),
        candidates,
        rejected,
        seconds: started.elapsed().as_secs_f64(),
    };
    info!("wrote {} templates to {} in {:.1} s", report.templates, opts.out.display(), report.seconds);
    Ok(report)
}

/// Selects over every ortho group while a thread of its own inserts the
/// templates with `writer` (and finishes the file); the tallies per level and
/// the database's summary. On an error the writer stops and its file is left
/// for the caller's temporary folder to remove.
fn select_and_write(
    ctx: &BuildCtx,
    groups: &[OrthoGroup],
    mut writer: trn_store::DbWriter,
) -> Result<(Vec<LevelTally>, trn_store::DbSummary)> {
    let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<Template>>(64);
    let abort = Arc::new(AtomicBool::new(false));
    let writer_abort = abort.clone();
    let writer_thread = std::thread::spawn(move || -> Result<trn_store::DbSummary> {
        for mut batch in rx {
            if writer_abort.load(Ordering::Relaxed) {
                return Err(BuildError::Cancelled);
            }
            writer.insert_batch(&mut batch)?;
        }
        if writer_abort.load(Ordering::Relaxed) {
            return Err(BuildError::Cancelled);
        }
        Ok(writer.finish()?)
    });
    let selected = select_all(ctx, groups, &tx);
    drop(tx);
    let tallies = match selected {
        Ok(r) => r,
        Err(e) => {
            abort.store(true, Ordering::Relaxed);
            // The writer's own error explains a closed channel better.
            return match writer_thread.join() {
                Ok(Err(we)) if matches!(e, BuildError::WriterStopped) => Err(we),
                _ => Err(e),
            };
        }
    };
    let summary = writer_thread.join().map_err(|_| BuildError::WriterStopped)??;
    Ok((tallies, summary))
}

/// The folder of `--out`, which must exist.
fn out_dir_of(opts: &BuildOptions) -> Result<PathBuf> {
    let out_dir = match opts.out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if !out_dir.is_dir() {
        return Err(BuildError::Option {
            option: "--out",
            reason: format!("folder {} does not exist", out_dir.display()),
        });
    }
    Ok(out_dir)
}

/// Opens and checks every ortho (and its luminance bands) and DEM, and that
/// they overlap, before any work.
fn open_inputs(opts: &BuildOptions) -> Result<Inputs> {
    let mut ortho_infos = Vec::new();
    for p in &opts.orthos {
        let (ds, info) = source::inspect(p)?;
        source::check_not_all_nodata(&ds, p)?;
        let lum = source::luminance_for(&ds, &info, opts.ortho_bands.as_deref())?;
        info!(
            "ortho {}: {}x{} px, {} band(s) {}, {:.2} x {:.2} m pixels",
            p.display(),
            info.width,
            info.height,
            info.band_count,
            info.band_type,
            info.pixel_dx_m,
            info.pixel_dy_m
        );
        ortho_infos.push((info, lum));
    }
    let dems = opts.dem.open()?;
    check_overlap(&ortho_infos.iter().map(|o| &o.0).collect::<Vec<_>>(), &dems)?;
    Ok(Inputs { orthos: ortho_infos, dems })
}

/// The checked inputs of a build.
struct Inputs {
    orthos: Vec<(RasterInfo, Luminance)>,
    dems: Vec<DemSpec>,
}

/// The ladder's base ground sample distance: `--base-gsd`, or the coarsest
/// ortho pixel rounded up to three significant digits (readable level GSDs).
fn base_gsd_of(opts: &BuildOptions, groups: &[OrthoGroup]) -> Result<f64> {
    let base_gsd = opts.base_gsd_m.unwrap_or_else(|| {
        let g = groups.iter().map(|g| g.info.pixel_dx_m.max(g.info.pixel_dy_m)).fold(0.0, f64::max);
        let mag = 10f64.powf(g.log10().floor() - 2.0);
        (g / mag).ceil() * mag
    });
    let finest = groups.iter().map(|g| g.info.pixel_dx_m.min(g.info.pixel_dy_m)).fold(f64::MAX, f64::min);
    if base_gsd < 0.5 * finest {
        return Err(BuildError::Option {
            option: "--base-gsd",
            reason: format!("{base_gsd} m is finer than half the finest ortho pixel ({finest:.3} m)"),
        });
    }
    Ok(base_gsd)
}

/// Logs the ladder, and warns where the ortho is too coarse for the finest
/// camera resolution asked for.
fn log_ladder(specs: &[LevelSpec], range: &GsdRange, serves: Option<&GsdRange>, base_gsd: f64) {
    info!(
        "sized for camera resolutions {:.2}..{:.1} m/px; {} levels: {}",
        range.finest_m,
        range.coarsest_m,
        specs.len(),
        specs
            .iter()
            .map(|l| format!("{} px at {} m ({:.0} m)", l.size_px, l.gsd_m, l.footprint_m()))
            .collect::<Vec<_>>()
            .join(", ")
    );
    if let Some(s) = serves {
        if s.finest_m > range.finest_m * 1.001 {
            warn!(
                "the ortho's pixels ({base_gsd} m) cannot serve camera resolutions finer than {:.2} m/px \
                 (asked for {:.2}): templates will span more than {} image pixels there",
                s.finest_m,
                range.finest_m,
                sizing::MAX_SPAN_PX
            );
        }
    }
}

/// The report of every level of the ladder (with the stored counts; logged),
/// the rejections by reason over all levels, and the candidates offered.
fn level_reports(
    specs: &[LevelSpec],
    fills: &[sizing::FillWindow],
    tallies: &[LevelTally],
    summary: &trn_store::DbSummary,
) -> (Vec<LevelReport>, BTreeMap<String, usize>, usize) {
    let mut rejected: BTreeMap<String, usize> = BTreeMap::new();
    let mut candidates = 0;
    let per_level: Vec<LevelReport> = specs
        .iter()
        .zip(tallies)
        .zip(fills)
        .map(|((s, t), fill)| {
            let n = summary.levels.iter().find(|l| l.level == s.level).map(|l| l.count as usize).unwrap_or(0);
            let level_rejected: BTreeMap<String, usize> =
                t.rejected.iter().map(|(k, v)| (format!("{k:?}"), *v)).collect();
            for (k, v) in &level_rejected {
                *rejected.entry(k.clone()).or_default() += v;
            }
            candidates += n + t.rejected.values().sum::<usize>();
            let km2 = t.covered_m2 / 1e6;
            LevelReport {
                level: s.level,
                gsd_m: s.gsd_m,
                template_px: s.size_px,
                footprint_m: s.footprint_m(),
                cell_m: t.cell_area_m2.sqrt(),
                fill_share: fill.share,
                templates: n,
                covered_km2: km2,
                per_km2: if km2 > 0.0 { n as f64 / km2 } else { 0.0 },
                serves_gsd_m: s.serves(),
                empty_cells: BTreeMap::from([
                    ("no_texture".to_string(), t.cells.no_texture),
                    ("not_unique".to_string(), t.cells.not_unique),
                    ("refused".to_string(), t.cells.refused),
                ]),
                rejected: level_rejected,
                mean_shading_share: if t.cells.taken > 0 {
                    t.shading_sum / t.cells.taken as f64
                } else {
                    0.0
                },
            }
        })
        .collect();
    for l in &per_level {
        info!(
            "level {} ({} px at {} m, {:.0} m, fill {}): {} templates, {:.2} per km² over {:.0} km²; empty cells {:?}; rejected {:?}",
            l.level,
            l.template_px,
            l.gsd_m,
            l.footprint_m,
            l.fill_share,
            l.templates,
            l.per_km2,
            l.covered_km2,
            l.empty_cells,
            l.rejected
        );
    }
    (per_level, rejected, candidates)
}

/// What every ortho group of a build shares.
struct BuildCtx<'a> {
    opts: &'a BuildOptions,
    dems: &'a [DemSpec],
    suns: &'a [SunGrid],
    /// Ground sample distance of the ladder's first step (m).
    base_gsd: f64,
    specs: &'a [LevelSpec],
    /// The build's temporary folder (pyramid levels, mosaics).
    work: &'a Path,
    cancel: &'a AtomicBool,
    progress: &'a (dyn Fn(Progress) + Sync),
}

/// Runs the selection over every ortho group, streaming templates to the
/// writer; from the second group on, a template closer to one of an earlier
/// group's (same level) than [`Dedupe`] allows is a duplicate where mosaics of
/// different bands overlap, and is dropped (the earlier group's is kept).
fn select_all(
    ctx: &BuildCtx,
    groups: &[OrthoGroup],
    tx: &SyncSender<Vec<Template>>,
) -> Result<Vec<LevelTally>> {
    let opts = ctx.opts;
    let mut tallies = vec![LevelTally::default(); ctx.specs.len()];
    let mut seen = Dedupe::default();
    let dropped = std::sync::atomic::AtomicUsize::new(0);
    for g in groups {
        let kept_here: Mutex<Vec<(u8, [f64; 3], f64)>> = Mutex::new(Vec::new());
        let sink = |mut batch: Vec<Template>| -> Result<()> {
            if !seen.is_empty() {
                let before = batch.len();
                batch.retain(|t| !seen.clashes(t, opts));
                dropped.fetch_add(before - batch.len(), Ordering::Relaxed);
            }
            if groups.len() > 1 {
                let mut k = kept_here.lock().unwrap_or_else(|e| e.into_inner());
                k.extend(
                    batch
                        .iter()
                        .map(|t| (t.level, t.center_ecef().0.into(), Dedupe::min_distance_m(t, opts))),
                );
            }
            if batch.is_empty() {
                return Ok(());
            }
            tx.send(batch).map_err(|_| BuildError::WriterStopped)
        };
        let tally = group::build_group(ctx, g, &sink)?;
        for (a, b) in tallies.iter_mut().zip(&tally) {
            a.merge(b);
        }
        for (level, ecef, min_d) in kept_here.into_inner().unwrap_or_else(|e| e.into_inner()) {
            seen.insert(level, ecef, min_d);
        }
    }
    if groups.len() > 1 {
        info!("dropped {} duplicate templates where mosaics overlap", dropped.load(Ordering::Relaxed));
    }
    Ok(tallies)
}

/// Landmarks kept from earlier ortho groups, on a grid per level: where
/// mosaics of different bands overlap, a template closer than half the
/// smallest default cell (a quarter of a template) or half `--spacing` to one
/// of them is a duplicate. Positions only (ECEF), so the index stays small
/// while the templates stream to the writer.
#[derive(Default)]
struct Dedupe {
    /// (level, ECEF cell) -> ECEF centres.
    grid: HashMap<(u8, i64, i64, i64), Vec<[f64; 3]>>,
}

impl Dedupe {
    fn min_distance_m(t: &Template, opts: &BuildOptions) -> f64 {
        0.5 * opts.spacing(t.width_px, 0.5) as f64 * t.gsd_m
    }

    fn is_empty(&self) -> bool {
        self.grid.is_empty()
    }

    /// Cells are 2^k metres, k per level from the first distance seen, so a
    /// 3 x 3 x 3 neighbourhood covers the distance looked for.
    fn key(level: u8, ecef: [f64; 3], cell_m: f64) -> (u8, i64, i64, i64) {
        let c = |v: f64| (v / cell_m).floor() as i64;
        (level, c(ecef[0]), c(ecef[1]), c(ecef[2]))
    }

    fn cell_of(min_d: f64) -> f64 {
        // A power of two at least min_d: the same for every template of a level.
        2f64.powi(min_d.max(1e-3).log2().ceil() as i32)
    }

    fn insert(&mut self, level: u8, ecef: [f64; 3], min_d: f64) {
        self.grid.entry(Self::key(level, ecef, Self::cell_of(min_d))).or_default().push(ecef);
    }

    fn clashes(&self, t: &Template, opts: &BuildOptions) -> bool {
        let min_d = Self::min_distance_m(t, opts);
        let cell = Self::cell_of(min_d);
        let p: [f64; 3] = t.center_ecef().0.into();
        let (l, x, y, z) = Self::key(t.level, p, cell);
        (-1..=1).any(|dx| {
            (-1..=1).any(|dy| {
                (-1..=1).any(|dz| {
                    self.grid.get(&(l, x + dx, y + dy, z + dz)).is_some_and(|v| {
                        v.iter().any(|q| {
                            let d2 = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2);
                            d2 < min_d * min_d
                        })
                    })
                })
            })
        })
    }
}

fn union_text(rasters: &[&RasterInfo]) -> String {
    rasters
        .iter()
        .map(|r| {
            let b = r.extent;
            format!(
                "{} lon {:.4}..{:.4} lat {:.4}..{:.4}",
                r.path.display(),
                b.min_lon_deg,
                b.max_lon_deg,
                b.min_lat_deg,
                b.max_lat_deg
            )
        })
        .collect::<Vec<_>>()
        .join("; ")
}

fn check_overlap(orthos: &[&RasterInfo], dems: &[DemSpec]) -> Result<()> {
    let any = orthos.iter().any(|o| dems.iter().any(|d| o.extent.intersection(&d.info.extent).is_some()));
    if any {
        return Ok(());
    }
    Err(BuildError::NoOverlap {
        ortho: union_text(orthos),
        dem: union_text(&dems.iter().map(|d| &d.info).collect::<Vec<_>>()),
    })
}

fn group_orthos(infos: Vec<(RasterInfo, Luminance)>, work: &Path) -> Result<Vec<OrthoGroup>> {
    let mut buckets: Vec<Vec<(RasterInfo, Luminance)>> = Vec::new();
    for (info, lum) in infos {
        let same = |o: &(RasterInfo, Luminance)| {
            o.0.srs_wkt == info.srs_wkt
                && (o.0.to_crs.gt[1] - info.to_crs.gt[1]).abs() < 1e-9 * info.to_crs.gt[1].abs()
                && (o.0.to_crs.gt[5] - info.to_crs.gt[5]).abs() < 1e-9 * info.to_crs.gt[5].abs()
                && o.0.to_crs.gt[2] == 0.0
                && info.to_crs.gt[2] == 0.0
                && o.0.band_count == info.band_count
                && o.0.band_type == info.band_type
                && o.1.bands == lum.bands
                && o.1.alpha_band == lum.alpha_band
        };
        match buckets.iter_mut().find(|b| same(&b[0])) {
            Some(b) => b.push((info, lum)),
            None => buckets.push(vec![(info, lum)]),
        }
    }
    // Buckets with the same bands in other CRSs or pixel sizes join the
    // finest one's mosaic, warped onto its grid: one raster, no seam.
    let mut order: Vec<usize> = (0..buckets.len()).collect();
    order.sort_by(|&a, &b| {
        let area = |k: usize| buckets[k][0].0.pixel_dx_m * buckets[k][0].0.pixel_dy_m;
        area(a).total_cmp(&area(b))
    });
    let joins = |host: &(RasterInfo, Luminance), o: &(RasterInfo, Luminance)| {
        host.0.to_crs.gt[2] == 0.0
            && host.0.to_crs.gt[4] == 0.0
            && o.0.band_count == host.0.band_count
            && o.0.band_type == host.0.band_type
            && o.1.bands == host.1.bands
            && o.1.alpha_band == host.1.alpha_band
    };
    // (host bucket, buckets warped onto it), hosts in input order.
    let mut mosaics: Vec<(usize, Vec<usize>)> = Vec::new();
    for &k in &order {
        match mosaics.iter_mut().find(|(h, _)| joins(&buckets[*h][0], &buckets[k][0])) {
            Some((_, warped)) => warped.push(k),
            None => mosaics.push((k, Vec::new())),
        }
    }
    mosaics.sort_by_key(|m| m.0);
    let mut groups = Vec::new();
    for (i, (host, warped)) in mosaics.into_iter().enumerate() {
        let host_info = buckets[host][0].0.clone();
        let mut sources: Vec<PathBuf> = Vec::new();
        for &k in &warped {
            let vrt = work.join(format!("ortho-warp-{i}-{k}.vrt"));
            let infos: Vec<RasterInfo> = buckets[k].iter().map(|x| x.0.clone()).collect();
            source::warp_onto_grid(&infos, &host_info, &vrt)?;
            sources.push(vrt);
        }
        let b: Vec<&(RasterInfo, Luminance)> =
            buckets[host].iter().chain(warped.iter().flat_map(|&k| buckets[k].iter())).collect();
        // Warped sources first: the host's own pixels lie on top where they overlap.
        sources.extend(buckets[host].iter().map(|x| x.0.path.clone()));
        let files: Vec<PathBuf> = b.iter().map(|x| x.0.path.clone()).collect();
        let (path, info) = if sources.len() == 1 {
            (host_info.path.clone(), host_info)
        } else {
            // One VRT per mosaic: templates may straddle file seams.
            let vrt = work.join(format!("ortho-mosaic-{i}.vrt"));
            source::build_vrt(&vrt, &sources, &files[0], "orthos")?;
            let (_, info) = source::inspect(&vrt)?;
            if warped.is_empty() {
                info!("mosaic of {} orthos: {}x{} px", files.len(), info.width, info.height);
            } else {
                info!(
                    "mosaic of {} orthos, {} of them warped onto the grid of {}: {}x{} px",
                    files.len(),
                    files.len() - buckets[host].len(),
                    host_info.path.display(),
                    info.width,
                    info.height
                );
            }
            (vrt, info)
        };
        // One grey-level stretch for the whole mosaic: the union of its files' ranges.
        let (lo, hi) = b.iter().fold((f32::MAX, f32::MIN), |(lo, hi), (_, l)| {
            (lo.min(l.offset), hi.max(l.offset + 255.0 / l.scale))
        });
        let lum = Luminance { offset: lo, scale: 255.0 / (hi - lo), ..buckets[host][0].1.clone() };
        groups.push(OrthoGroup { index: i as u32, path, info, lum, files });
    }
    Ok(groups)
}

/// The lighting grids of `opts.suns` over the orthos, at the finest DEM's
/// spacing (none without suns).
fn render_suns(opts: &BuildOptions, groups: &[OrthoGroup], dems: &[DemSpec]) -> Result<Vec<SunGrid>> {
    if opts.suns.is_empty() {
        return Ok(Vec::new());
    }
    let started = Instant::now();
    let bbox = groups.iter().skip(1).fold(groups[0].info.extent, |b, g| {
        let e = &g.info.extent;
        GeoBox::new(
            b.min_lon_deg.min(e.min_lon_deg),
            b.min_lat_deg.min(e.min_lat_deg),
            b.max_lon_deg.max(e.max_lon_deg),
            b.max_lat_deg.max(e.max_lat_deg),
        )
    });
    let spacing_m = dems.iter().map(|d| d.info.pixel_dx_m.min(d.info.pixel_dy_m)).fold(f64::MAX, f64::min);
    let sampler = terrain::DemSampler::open(dems)?;
    let grids = SunGrid::render(&sampler, &bbox, spacing_m, &opts.suns);
    let (rows, cols) = grids[0].shape();
    info!(
        "lighting of {} sun(s) on {rows} x {cols} DEM nodes ({:.0} m apart) in {:.2} s",
        grids.len(),
        spacing_m,
        started.elapsed().as_secs_f64()
    );
    Ok(grids)
}

fn metadata(
    opts: &BuildOptions,
    groups: &[OrthoGroup],
    dems: &[DemSpec],
    base_gsd: f64,
    specs: &[LevelSpec],
) -> Vec<(String, serde_json::Value)> {
    use serde_json::json;
    let sources: Vec<_> = groups
        .iter()
        .map(|g| {
            json!({
                "index": g.index,
                "files": g.files,
                "width": g.info.width, "height": g.info.height,
                "band_type": g.info.band_type,
                "luminance_bands": g.lum.bands,
                "pixel_dx_m": g.info.pixel_dx_m, "pixel_dy_m": g.info.pixel_dy_m,
                "crs_wkt": g.info.srs_wkt,
            })
        })
        .collect();
    let dem_meta: Vec<_> = dems
        .iter()
        .map(|d| {
            json!({
                "file": d.info.path,
                "crs_wkt": d.info.srs_wkt,
                "pixel_dx_m": d.info.pixel_dx_m, "pixel_dy_m": d.info.pixel_dy_m,
                "to_metres": d.to_metres,
                "vertical_conversion": d.geoid.as_ref().map(|g| format!("orthometric + geoid grid {}", g.name))
                    .unwrap_or_else(|| "none (ellipsoidal)".into()),
            })
        })
        .collect();
    let level_list: Vec<_> = specs
        .iter()
        .map(|s| json!({"level": s.level, "gsd_m": s.gsd_m, "template_px": s.size_px, "footprint_m": s.footprint_m()}))
        .collect();
    let created =
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    vec![
        ("sources".into(), json!(sources)),
        ("dems".into(), json!(dem_meta)),
        ("height_reference".into(), json!("WGS84 ellipsoid")),
        ("parameters".into(), serde_json::to_value(opts).unwrap_or_default()),
        ("base_gsd_m".into(), json!(base_gsd)),
        ("sized_for_gsd_m".into(), json!(opts.gsd_range())),
        ("max_view_deg".into(), json!(opts.max_view_deg())),
        ("suns".into(), json!(opts.suns)),
        ("levels".into(), json!(level_list)),
        ("created_unix".into(), json!(created)),
        ("trn_version".into(), json!(env!("CARGO_PKG_VERSION"))),
    ]
}

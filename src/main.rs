//! `trn`: the command line of the landmark system (build, and more to come).

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use clap::{Parser, Subcommand, ValueEnum};
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

#[derive(Subcommand)]
enum Command {
    /// Cut orthoimagery and DEMs into a landmark database (SQLite/GeoPackage).
    Build(BuildArgs),
    /// Write a synthetic ortho + DEM pair (GeoTIFF) for tests and benchmarks.
    Synth(SynthArgs),
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

#[derive(clap::Args)]
struct BuildArgs {
    /// Orthoimage(s): any GDAL raster, any CRS; several files form a mosaic.
    #[arg(long = "ortho", required = true, num_args = 1..)]
    orthos: Vec<PathBuf>,
    /// Elevation model(s): any GDAL raster, any CRS.
    #[arg(long = "dem", required = true, num_args = 1..)]
    dems: Vec<PathBuf>,
    /// Output database (replaced atomically when the build succeeds).
    #[arg(long)]
    out: PathBuf,
    /// Bands making the luminance: one (grey) or three (red,green,blue), e.g. 3,2,1.
    #[arg(long, value_delimiter = ',')]
    ortho_bands: Option<Vec<usize>>,
    /// Vertical datum of the DEM heights when the file does not say (or to override it).
    #[arg(long, value_enum)]
    dem_vertical: Option<VerticalArg>,
    /// Geoid grid (GDAL-readable: .gtx, .tif) for --dem-vertical geoid; default for EGM96 is Debian's.
    #[arg(long)]
    geoid: Option<PathBuf>,
    /// Template side in pixels.
    #[arg(long, default_value_t = 32)]
    template_size: u32,
    /// Landmark spacing: one cell of this many template pixels gets --per-cell landmarks.
    #[arg(long, default_value_t = 64)]
    spacing: u32,
    #[arg(long, default_value_t = 1)]
    per_cell: usize,
    /// Number of levels (GSD doubles per level); default: up to --max-gsd.
    #[arg(long)]
    levels: Option<u8>,
    /// Coarsest level GSD (m) when --levels is not given.
    #[arg(long, default_value_t = 64.0)]
    max_gsd: f64,
    /// GSD of level 0 (m); default: the coarsest ortho pixel size.
    #[arg(long)]
    base_gsd: Option<f64>,
    /// Minimum grey-level standard deviation of a template.
    #[arg(long, default_value_t = 6.0)]
    min_contrast: f32,
    /// Minimum Shi-Tomasi strength (smaller structure-tensor eigenvalue).
    #[arg(long, default_value_t = 2.0)]
    min_shi_tomasi: f32,
    /// Uniqueness search radius (template pixels).
    #[arg(long, default_value_t = 8)]
    search_radius: u32,
    /// Highest NCC of a template against its surroundings (away from itself).
    #[arg(long, default_value_t = 0.9)]
    max_second_peak: f32,
    /// Largest RMS terrain distance from the template plane, in GSDs.
    #[arg(long, default_value_t = 0.5)]
    max_relief: f64,
    /// Worker threads (default: all cores).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
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
}

#[derive(Clone, Copy, ValueEnum)]
enum CompressArg {
    Deflate,
    Jpeg,
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
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Build(a) => run_build(a),
        Command::Synth(a) => run_synth(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run_build(a: BuildArgs) -> anyhow::Result<()> {
    if let Some(n) = a.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n as usize).build_global()?;
    }
    let cancel = Arc::new(AtomicBool::new(false));
    let flag = cancel.clone();
    // First Ctrl-C stops between tiles and cleans up; the output is never half-written.
    ctrlc::set_handler(move || flag.store(true, Ordering::Relaxed))?;
    let mut o = BuildOptions::new(a.orthos, a.dems, a.out);
    o.ortho_bands = a.ortho_bands;
    o.dem_vertical = a.dem_vertical.map(|v| match v {
        VerticalArg::Egm96 => DemVertical::Egm96,
        VerticalArg::Ellipsoid => DemVertical::Ellipsoid,
        VerticalArg::Geoid => DemVertical::Geoid,
    });
    o.geoid = a.geoid;
    o.template_size = a.template_size;
    o.spacing_px = a.spacing;
    o.per_cell = a.per_cell;
    o.levels = a.levels;
    o.max_gsd_m = a.max_gsd;
    o.base_gsd_m = a.base_gsd;
    o.min_contrast_std = a.min_contrast;
    o.min_shi_tomasi = a.min_shi_tomasi;
    o.search_radius_px = a.search_radius;
    o.max_second_peak = a.max_second_peak;
    o.max_relief_gsd = a.max_relief;
    let report = trn_builder::build(&o, &cancel)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

fn run_synth(a: SynthArgs) -> anyhow::Result<()> {
    use trn_builder::synth::{write_dem, write_ortho, SynthGrid};
    let ortho = SynthGrid {
        epsg: 32613,
        geo_transform: [a.east, a.gsd, 0.0, a.north, 0.0, -a.gsd],
        width: a.size,
        height: a.size,
    };
    let compression = match a.compress {
        CompressArg::Deflate => trn_builder::synth::Compression::Deflate,
        CompressArg::Jpeg => trn_builder::synth::Compression::Jpeg,
    };
    write_ortho(&a.ortho, &ortho, 3, a.seed, a.nodata_border, compression)?;
    // DEM at 15x the ortho pixel, covering the same area with a margin.
    let dem_gsd = a.gsd * 15.0;
    let n = (a.size as f64 * a.gsd / dem_gsd).ceil() as usize + 4;
    let dem = SynthGrid {
        epsg: 32613,
        geo_transform: [a.east - 2.0 * dem_gsd, dem_gsd, 0.0, a.north + 2.0 * dem_gsd, 0.0, -dem_gsd],
        width: n,
        height: n,
    };
    write_dem(&a.dem, &dem, a.seed + 100, 1500.0, 60.0)?;
    println!("wrote {} and {}", a.ortho.display(), a.dem.display());
    Ok(())
}

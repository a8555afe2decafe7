//! Times `DbWriter::insert_batch` and `DbWriter::finish` on synthetic templates shaped
//! like a real build: 32 x 32 px, a 9 x 9 height grid, footprints spread over a 5 km
//! square, emitted tile by tile (as the builder's tiles finish) in batches of ~500.
//!
//! ```text
//! cargo run --release -p trn-store --example insert_bench -- [N] [REPEATS]
//! ```
//! N templates (default 30000); each run writes a new file in the temp directory, and
//! the best of REPEATS runs (default 3) is printed: wall time and this thread's CPU time
//! (Linux), which the load of a shared machine disturbs less. With `KEEP=1` in the
//! environment the files are kept (and their paths printed) for inspection.

use std::time::Instant;

use trn_geodesy::{metres_per_degree, Geodetic};
use trn_landmark::{GeoBox, HeightGrid, Template, TemplateQuality, TerrainPatch};
use trn_store::DbWriter;

const PX: u32 = 32;
const GRID_N: u32 = 9;
const AREA_M: f64 = 5000.0;
const TILE_M: f64 = 512.0;
const BATCH: usize = 500;

/// SplitMix64: deterministic and good enough for test data.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }
}

fn template(rng: &mut Rng, level: u8, east_m: f64, north_m: f64) -> Template {
    let (lat0, lon0) = (46.5, 7.5);
    let (m_per_lat, m_per_lon) = metres_per_degree(lat0);
    let lat = lat0 + north_m / m_per_lat;
    let lon = lon0 + east_m / m_per_lon;
    let gsd_m = 0.5 * f64::from(1u32 << level);
    let half_m = f64::from(PX) * gsd_m / 2.0;
    let footprint = GeoBox::new(
        lon - half_m / m_per_lon,
        lat - half_m / m_per_lat,
        lon + half_m / m_per_lon,
        lat + half_m / m_per_lat,
    );
    let (nx, ny) = (rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3));
    let norm = (nx * nx + ny * ny + 1.0).sqrt();
    Template {
        id: 0,
        level,
        gsd_m,
        width_px: PX,
        height_px: PX,
        center: Geodetic::new(lat, lon, rng.uniform(400.0, 3000.0)),
        footprint,
        terrain: TerrainPatch {
            plane_normal_enu: [nx / norm, ny / norm, 1.0 / norm],
            plane_residual_rms_m: rng.uniform(0.0, 5.0),
            height_grid: HeightGrid {
                n: GRID_N,
                spacing_m: 2.0 * half_m / f64::from(GRID_N - 1),
                heights_m: (0..GRID_N * GRID_N).map(|_| rng.uniform(-20.0, 20.0) as f32).collect(),
            },
        },
        quality: TemplateQuality {
            shi_tomasi: rng.uniform(0.0, 500.0) as f32,
            contrast_std: rng.uniform(5.0, 60.0) as f32,
            second_peak_ncc: rng.uniform(0.0, 0.9) as f32,
            shading_share: rng.uniform(0.0, 1.0) as f32,
        },
        source: 0,
        lighting: 0,
        pixels: (0..PX * PX).map(|_| rng.next_u64() as u8).collect(),
    }
}

/// `n` templates, tile by tile in row-major tile order, random inside each tile; level
/// k gets about half as many as level k - 1.
fn templates(n: usize) -> Vec<Template> {
    let mut rng = Rng(42);
    let tiles_per_side = (AREA_M / TILE_M).ceil() as usize;
    let tiles = tiles_per_side * tiles_per_side;
    let mut out = Vec::with_capacity(n);
    for tile in 0..tiles {
        let (tx, ty) = ((tile % tiles_per_side) as f64 * TILE_M, (tile / tiles_per_side) as f64 * TILE_M);
        let count = n * (tile + 1) / tiles - n * tile / tiles;
        for _ in 0..count {
            let level = (-rng.unit().max(1e-9).log2()).floor().min(4.0) as u8;
            let (east_m, north_m) = (tx + rng.uniform(0.0, TILE_M), ty + rng.uniform(0.0, TILE_M));
            out.push(template(&mut rng, level, east_m, north_m));
        }
    }
    out
}

/// CPU time of this thread (Linux schedstat, ns resolution), or `None` elsewhere.
fn thread_cpu_s() -> Option<f64> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    Some(text.split_whitespace().next()?.parse::<f64>().ok()? * 1e-9)
}

/// Wall and CPU seconds of `f`.
fn timed<T>(f: impl FnOnce() -> T) -> (T, f64, f64) {
    let (t0, c0) = (Instant::now(), thread_cpu_s());
    let out = f();
    let wall = t0.elapsed().as_secs_f64();
    let cpu = thread_cpu_s().zip(c0).map_or(wall, |(c1, c0)| c1 - c0);
    (out, wall, cpu)
}

fn main() {
    let mut args = std::env::args().skip(1);
    let n: usize = args.next().map_or(30_000, |a| a.parse().expect("N: a number of templates"));
    let repeats: usize = args.next().map_or(3, |a| a.parse().expect("REPEATS: a number"));
    let originals = templates(n);
    let dir = std::env::temp_dir().join(format!("trn-insert-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // Best (lowest) of the repeats: [insert wall, insert CPU, finish wall, finish CPU].
    let mut best = [f64::MAX; 4];
    for run in 0..repeats {
        let mut batch_src = originals.clone();
        let path = dir.join(format!("bench-{run}.gpkg"));
        let mut w = DbWriter::create(&path).unwrap();
        let ((), insert_wall, insert_cpu) = timed(|| {
            for batch in batch_src.chunks_mut(BATCH) {
                w.insert_batch(batch).unwrap();
            }
        });
        let (summary, finish_wall, finish_cpu) = timed(|| w.finish().unwrap());
        assert_eq!(summary.template_count, n as u64);
        println!(
            "run {run}: insert {:.2} us/template (CPU {:.2}), finish {:.3} s (CPU {:.3}), file {:.1} MB",
            insert_wall * 1e6 / n as f64,
            insert_cpu * 1e6 / n as f64,
            finish_wall,
            finish_cpu,
            summary.file_size_bytes as f64 / 1e6
        );
        for (b, v) in best.iter_mut().zip([insert_wall, insert_cpu, finish_wall, finish_cpu]) {
            *b = b.min(v);
        }
        if std::env::var_os("KEEP").is_some() {
            println!("kept {}", path.display());
            continue;
        }
        std::fs::remove_file(&path).unwrap();
    }
    std::fs::remove_dir(&dir).ok();
    println!(
        "best of {repeats}: insert {:.2} us/template (CPU {:.2}), {:.3} s for {n}; finish {:.3} s (CPU {:.3})",
        best[0] * 1e6 / n as f64,
        best[1] * 1e6 / n as f64,
        best[0],
        best[2],
        best[3]
    );
}

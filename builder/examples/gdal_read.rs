//! Baseline for the builder benchmark: the time GDAL alone takes to read every
//! band of a raster once, in its native type, in strips of whole block rows.
//! Usage: gdal_read RASTER [RUNS]  (prints the best wall time in seconds)

use std::time::Instant;

use gdal::raster::GdalDataType;
use gdal::Dataset;

fn read_all(path: &str) -> gdal::errors::Result<u64> {
    // A fresh dataset per run: GDAL's block cache does not outlive it.
    let ds = Dataset::open(path)?;
    let (w, h) = ds.raster_size();
    let block_h = ds.rasterband(1)?.block_size().1.max(1);
    let strip = block_h * (256 / block_h).max(1);
    let mut checksum = 0u64;
    let mut y = 0;
    while y < h {
        let rows = strip.min(h - y);
        for b in 1..=ds.raster_count() {
            let band = ds.rasterband(b)?;
            match band.band_type() {
                GdalDataType::UInt8 => {
                    let buf = band.read_as::<u8>((0, y as isize), (w, rows), (w, rows), None)?;
                    checksum = checksum.wrapping_add(buf.data()[0] as u64);
                }
                _ => {
                    let buf = band.read_as::<f32>((0, y as isize), (w, rows), (w, rows), None)?;
                    checksum = checksum.wrapping_add(buf.data()[0] as u64);
                }
            }
        }
        y += rows;
    }
    Ok(checksum)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let path = args.get(1).expect("usage: gdal_read RASTER [RUNS]");
    let runs: usize = args.get(2).and_then(|r| r.parse().ok()).unwrap_or(3);
    let mut best = f64::MAX;
    for _ in 0..runs {
        let t = Instant::now();
        let c = read_all(path).unwrap_or_else(|e| panic!("{path}: {e}"));
        std::hint::black_box(c);
        best = best.min(t.elapsed().as_secs_f64());
    }
    println!("{best:.3}");
}

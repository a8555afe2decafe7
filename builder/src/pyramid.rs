//! The luminance pyramid above level 0: each coarser level from the level
//! below (2x2 box filter), kept in memory or, past a budget, in raw
//! temporary files, so memory stays bounded by the window size. Level 0 is
//! the ortho itself ([`trn_raster::ortho::OrthoReader`]).

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::RwLock;

use trn_raster::ortho::Window;

use crate::error::{BuildError, Result};

/// A pyramid level: f32 luminance and u8 validity, in memory when it fits the
/// budget, else in two raw temporary files (memory stays bounded either way).
pub struct LevelFile {
    pub width: usize,
    pub height: usize,
    path: PathBuf,
    store: LevelStore,
}

enum LevelStore {
    Memory(RwLock<(Vec<f32>, Vec<u8>)>),
    Files { lum: File, valid: File },
}

/// Largest pyramid level kept in memory (bytes).
pub const LEVEL_MEMORY_BUDGET: usize = 768 << 20;

impl LevelFile {
    pub fn create(dir: &Path, name: &str, width: usize, height: usize) -> Result<Self> {
        let lp = dir.join(format!("{name}.lum"));
        if width * height * 5 <= LEVEL_MEMORY_BUDGET {
            let store =
                LevelStore::Memory(RwLock::new((vec![0f32; width * height], vec![0u8; width * height])));
            return Ok(Self { width, height, path: lp, store });
        }
        let io = |p: &Path| {
            let p = p.to_path_buf();
            move |source| BuildError::Io { path: p.clone(), source }
        };
        let vp = dir.join(format!("{name}.valid"));
        let lum =
            File::options().read(true).write(true).create(true).truncate(true).open(&lp).map_err(io(&lp))?;
        let valid =
            File::options().read(true).write(true).create(true).truncate(true).open(&vp).map_err(io(&vp))?;
        lum.set_len((width * height * 4) as u64).map_err(io(&lp))?;
        valid.set_len((width * height) as u64).map_err(io(&vp))?;
        Ok(Self { width, height, path: lp, store: LevelStore::Files { lum, valid } })
    }

    fn io_err(&self, source: std::io::Error) -> BuildError {
        BuildError::Io { path: self.path.clone(), source }
    }

    /// Writes a block whose rows are `width` long, at (x0, y0).
    pub fn write(&self, x0: usize, y0: usize, width: usize, lum: &[f32], valid: &[u8]) -> Result<()> {
        let rows = lum.len() / width.max(1);
        match &self.store {
            LevelStore::Memory(m) => {
                let mut g = m.write().unwrap_or_else(|e| e.into_inner());
                for r in 0..rows {
                    let off = (y0 + r) * self.width + x0;
                    g.0[off..off + width].copy_from_slice(&lum[r * width..(r + 1) * width]);
                    g.1[off..off + width].copy_from_slice(&valid[r * width..(r + 1) * width]);
                }
            }
            LevelStore::Files { lum: lf, valid: vf } => {
                for r in 0..rows {
                    let off = ((y0 + r) * self.width + x0) as u64;
                    let bytes: Vec<u8> =
                        lum[r * width..(r + 1) * width].iter().flat_map(|v| v.to_le_bytes()).collect();
                    lf.write_all_at(&bytes, off * 4).map_err(|e| self.io_err(e))?;
                    vf.write_all_at(&valid[r * width..(r + 1) * width], off).map_err(|e| self.io_err(e))?;
                }
            }
        }
        Ok(())
    }

    /// Reads a window into `win`, whose buffers are reused; pixels outside
    /// the level are invalid.
    pub fn read_into(
        &self,
        x0: isize,
        y0: isize,
        width: usize,
        height: usize,
        win: &mut Window,
    ) -> Result<()> {
        win.reset(x0, y0, width, height);
        let (rx0, rx1) = (x0.max(0), (x0 + width as isize).min(self.width as isize));
        let inside = rx0 == x0
            && rx1 == x0 + width as isize
            && y0 >= 0
            && y0 + height as isize <= self.height as isize;
        if !inside {
            win.lum.fill(0.0);
            win.valid.fill(0);
        }
        let (lum, valid) = (&mut win.lum, &mut win.valid);
        if rx1 > rx0 {
            let rw = (rx1 - rx0) as usize;
            let guard = match &self.store {
                LevelStore::Memory(m) => Some(m.read().unwrap_or_else(|e| e.into_inner())),
                LevelStore::Files { .. } => None,
            };
            let mut bytes = match guard {
                Some(_) => Vec::new(),
                None => vec![0u8; rw * 4],
            };
            for r in 0..height {
                let y = y0 + r as isize;
                if y < 0 || y >= self.height as isize {
                    continue;
                }
                let off = y as usize * self.width + rx0 as usize;
                let dst = r * width + (rx0 - x0) as usize;
                match (&self.store, &guard) {
                    (_, Some(g)) => {
                        lum[dst..dst + rw].copy_from_slice(&g.0[off..off + rw]);
                        valid[dst..dst + rw].copy_from_slice(&g.1[off..off + rw]);
                    }
                    (LevelStore::Files { lum: lf, valid: vf }, None) => {
                        lf.read_exact_at(&mut bytes, off as u64 * 4).map_err(|e| self.io_err(e))?;
                        for (c, ch) in bytes.chunks_exact(4).enumerate() {
                            lum[dst + c] = f32::from_le_bytes([ch[0], ch[1], ch[2], ch[3]]);
                        }
                        vf.read_exact_at(&mut valid[dst..dst + rw], off as u64)
                            .map_err(|e| self.io_err(e))?;
                    }
                    (LevelStore::Memory(_), None) => unreachable!("memory levels are always locked"),
                }
            }
        }
        Ok(())
    }
}

/// 2x2 box reduction of the `ow x oh` coarse pixels from window pixel (cx, cy),
/// into reused buffers; a coarse pixel is valid when all four are.
pub fn downsample2_into(
    win: &Window,
    cx: usize,
    cy: usize,
    ow: usize,
    oh: usize,
    lum: &mut Vec<f32>,
    valid: &mut Vec<u8>,
) {
    lum.resize(ow * oh, 0.0);
    valid.resize(ow * oh, 0);
    if ow == 0 {
        return;
    }
    for r in 0..oh {
        let i = (cy + 2 * r) * win.width + cx;
        let j = i + win.width;
        let (l0, l1) = (&win.lum[i..i + 2 * ow], &win.lum[j..j + 2 * ow]);
        let (v0, v1) = (&win.valid[i..i + 2 * ow], &win.valid[j..j + 2 * ow]);
        let (lo, vo) = (&mut lum[r * ow..(r + 1) * ow], &mut valid[r * ow..(r + 1) * ow]);
        for ((o, a), b) in lo.iter_mut().zip(l0.chunks_exact(2)).zip(l1.chunks_exact(2)) {
            *o = 0.25 * (a[0] + a[1] + b[0] + b[1]);
        }
        for ((o, va), vb) in vo.iter_mut().zip(v0.chunks_exact(2)).zip(v1.chunks_exact(2)) {
            *o = va[0] & va[1] & vb[0] & vb[1];
        }
    }
}

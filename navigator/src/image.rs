//! The camera image as the navigator uses it: grey levels in f32 with a 2x
//! box-filtered pyramid for coarse searches, and per-pixel undistorted
//! normalized coordinates (computed once per camera) so that templates are
//! warped into the distorted image without an undistortion per pixel.

use trn_camera::{CameraModel, Pixel};

/// A grey image, row-major.
#[derive(Clone, Debug)]
pub struct GreyImage {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl GreyImage {
    /// 2x2 box reduction: pixel (i, j) of the result is centred on
    /// (2i + 0.5, 2j + 0.5) of this image.
    pub fn reduce(&self) -> GreyImage {
        let (w, h) = (self.width / 2, self.height / 2);
        let mut data = vec![0f32; w * h];
        for (y, row) in data.chunks_exact_mut(w.max(1)).enumerate().take(h) {
            let (a, b) = (&self.data[2 * y * self.width..], &self.data[(2 * y + 1) * self.width..]);
            for (x, out) in row.iter_mut().enumerate() {
                *out = 0.25 * (a[2 * x] + a[2 * x + 1] + b[2 * x] + b[2 * x + 1]);
            }
        }
        GreyImage { width: w, height: h, data }
    }
}

/// Level k of the pyramid has pixels 2^k times larger; a full-resolution
/// position u maps to (u + 0.5) / 2^k - 0.5 there.
pub struct Pyramid {
    pub levels: Vec<GreyImage>,
}

impl Pyramid {
    pub fn new(image: GreyImage, levels: usize) -> Self {
        let mut v = vec![image];
        while v.len() < levels.max(1) {
            let last = v.last().expect("level 0");
            if last.width < 32 || last.height < 32 {
                break;
            }
            let next = last.reduce();
            v.push(next);
        }
        Self { levels: v }
    }
}

/// Full-resolution pixel position to level `k`.
pub fn to_level(p: Pixel, k: usize) -> Pixel {
    let s = (1u32 << k) as f64;
    Pixel::new((p.u + 0.5) / s - 0.5, (p.v + 0.5) / s - 0.5)
}

/// Level `k` pixel position to full resolution.
pub fn from_level(p: Pixel, k: usize) -> Pixel {
    let s = (1u32 << k) as f64;
    Pixel::new((p.u + 0.5) * s - 0.5, (p.v + 0.5) * s - 0.5)
}

/// Undistorted normalized coordinates `(x/z, y/z)` of every pixel of every
/// pyramid level (each level's pixel centres mapped back to full resolution).
pub struct UndistortLut {
    pub levels: Vec<(usize, usize, Vec<[f32; 2]>)>,
}

impl UndistortLut {
    pub fn new(camera: &CameraModel, levels: usize) -> Self {
        let mut out = Vec::new();
        let (mut w, mut h) = (camera.width as usize, camera.height as usize);
        for k in 0..levels {
            let mut v = Vec::with_capacity(w * h);
            for y in 0..h {
                for x in 0..w {
                    let p = from_level(Pixel::new(x as f64, y as f64), k);
                    let n = camera.pixel_to_normalized(p);
                    v.push([n.x as f32, n.y as f32]);
                }
            }
            out.push((w, h, v));
            (w, h) = (w / 2, h / 2);
            if w < 32 || h < 32 {
                break;
            }
        }
        Self { levels: out }
    }

    /// The rays of level `k`'s pixels `x..x + len` on row `y`.
    #[inline]
    pub fn row(&self, k: usize, y: usize, x: usize, len: usize) -> &[[f32; 2]] {
        let (w, _, v) = &self.levels[k];
        &v[y * w + x..][..len]
    }
}

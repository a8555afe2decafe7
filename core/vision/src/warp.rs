//! A grey template resampled through a plane's homography: the inner loop
//! of predicting a landmark's appearance in a camera image.
//!
//! Each output pixel looks along its normalized ray `(x, y)` (from an
//! undistortion table, so lens distortion is already in the ray); the
//! homography `h` (3x3, row-major) maps `(x, y, 1)` to the template pixel
//! `(column, row)` in homogeneous coordinates, and the template is sampled
//! there bilinearly. A pixel whose ray meets the plane behind the camera
//! (`w <= 0`) or off the template keeps no value.
//!
//! [`homography_row`] does one row of pixels: with AVX2 (chosen at run time)
//! four at a time in f64, in the same order of operations as the scalar
//! [`homography_sample`], so both give the same bits (tested): a caller's
//! results do not depend on the machine.
//!
//! ```
//! use trn_vision::warp::{homography_row, GreyTemplate};
//!
//! // A 4x4 ramp, seen through the identity (ray (x, y) = template (x, y)).
//! let pixels: Vec<u8> = (0..16).map(|i| (i % 4 * 10) as u8).collect();
//! let t = GreyTemplate { width: 4, height: 4, pixels: &pixels };
//! let h = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
//! let rays = [[0.5f32, 1.0], [2.25, 2.0], [3.5, 0.0]];
//! let (mut data, mut mask) = ([0f32; 3], [false; 3]);
//! homography_row(&t, &h, &rays, &mut data, &mut mask);
//! assert_eq!((data[0], data[1]), (5.0, 22.5));
//! assert!(mask[0] && mask[1] && !mask[2]); // column 3.5 is off the template
//! ```

/// A row-major 8-bit grey template (at least 2x2 pixels).
#[derive(Clone, Copy, Debug)]
pub struct GreyTemplate<'a> {
    pub width: usize,
    pub height: usize,
    pub pixels: &'a [u8],
}

/// The template's value at template pixel `(tc, tr)` (column, row),
/// bilinear; `None` outside `[0, width - 1] x [0, height - 1]` (NaN
/// included).
#[inline(always)]
pub fn bilinear(t: &GreyTemplate, tc: f64, tr: f64) -> Option<f32> {
    let (tw, th) = (t.width, t.height);
    if !(tc >= 0.0 && tr >= 0.0 && tc <= (tw - 1) as f64 && tr <= (th - 1) as f64) {
        return None;
    }
    let (ic, ir) = ((tc as usize).min(tw - 2), (tr as usize).min(th - 2));
    let (fc, fr) = ((tc - ic as f64) as f32, (tr - ir as f64) as f32);
    let rows = &t.pixels[ir * tw..][..2 * tw];
    let (a, b) = (&rows[ic..ic + 2], &rows[tw + ic..tw + ic + 2]);
    Some(
        (a[0] as f32 * (1.0 - fc) + a[1] as f32 * fc) * (1.0 - fr)
            + (b[0] as f32 * (1.0 - fc) + b[1] as f32 * fc) * fr,
    )
}

/// The template's value seen along normalized ray `n` through homography
/// `h` (row-major; ray `(x, y, 1)` -> template pixel, homogeneous); `None`
/// behind the camera or off the template.
#[inline(always)]
pub fn homography_sample(t: &GreyTemplate, h: &[f64; 9], n: [f32; 2]) -> Option<f32> {
    let (nx, ny) = (n[0] as f64, n[1] as f64);
    let mz = h[6] * nx + h[7] * ny + h[8];
    if mz > 0.0 {
        let (mx, my) = (h[0] * nx + h[1] * ny + h[2], h[3] * nx + h[4] * ny + h[5]);
        bilinear(t, mx / mz, my / mz)
    } else {
        None
    }
}

/// [`homography_sample`] along a row of rays: `data[i]` and `mask[i]` are
/// set where ray `i` sees the template, left as they are elsewhere.
pub fn homography_row(
    t: &GreyTemplate,
    h: &[f64; 9],
    rays: &[[f32; 2]],
    data: &mut [f32],
    mask: &mut [bool],
) {
    assert!(t.width >= 2 && t.height >= 2 && t.pixels.len() >= t.width * t.height, "template size");
    assert!(data.len() >= rays.len() && mask.len() >= rays.len(), "output row shorter than the rays");
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") && t.width * t.height < i32::MAX as usize {
        // SAFETY: the CPU supports AVX2 (just checked); the sizes are checked above.
        unsafe { avx2::homography_row(t, h, rays, data, mask) };
        return;
    }
    scalar_row(t, h, rays, data, mask);
}

fn scalar_row(t: &GreyTemplate, h: &[f64; 9], rays: &[[f32; 2]], data: &mut [f32], mask: &mut [bool]) {
    for ((d, m), &n) in data.iter_mut().zip(mask.iter_mut()).zip(rays) {
        if let Some(v) = homography_sample(t, h, n) {
            (*d, *m) = (v, true);
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::GreyTemplate;
    use std::arch::x86_64::*;

    /// Four rays at a time, each step as the scalar code takes it (no fused
    /// multiply-add: the products are rounded before the sums, as there).
    #[target_feature(enable = "avx2")]
    pub(super) fn homography_row(
        t: &GreyTemplate,
        h: &[f64; 9],
        rays: &[[f32; 2]],
        data: &mut [f32],
        mask: &mut [bool],
    ) {
        let (tw, th) = (t.width, t.height);
        let hv: [__m256d; 9] = std::array::from_fn(|i| _mm256_set1_pd(h[i]));
        let (zero, one) = (_mm256_setzero_pd(), _mm_set1_ps(1.0));
        let (c_max, r_max) = (_mm256_set1_pd((tw - 1) as f64), _mm256_set1_pd((th - 1) as f64));
        let (ic_max, ir_max) = (_mm_set1_epi32(tw as i32 - 2), _mm_set1_epi32(th as i32 - 2));
        let deinterleave = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);
        let chunks = rays.len() / 4;
        for q in 0..chunks {
            let k = 4 * q;
            let four: &[[f32; 2]; 4] = rays[k..k + 4].try_into().expect("four rays");
            // SAFETY: `four` is 8 contiguous f32 (32 bytes); unaligned load.
            let xy = unsafe { _mm256_loadu_ps(four.as_ptr().cast::<f32>()) };
            let xy = _mm256_permutevar8x32_ps(xy, deinterleave);
            let nx = _mm256_cvtps_pd(_mm256_castps256_ps128(xy));
            let ny = _mm256_cvtps_pd(_mm256_extractf128_ps::<1>(xy));
            // (A macro, not a closure: a closure would not inherit AVX2.)
            macro_rules! dot {
                ($a:expr, $b:expr, $c:expr) => {
                    _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd($a, nx), _mm256_mul_pd($b, ny)), $c)
                };
            }
            let mz = dot!(hv[6], hv[7], hv[8]);
            let tc = _mm256_div_pd(dot!(hv[0], hv[1], hv[2]), mz);
            let tr = _mm256_div_pd(dot!(hv[3], hv[4], hv[5]), mz);
            // In front of the camera, and on the template (NaN fails every test).
            let ok = _mm256_and_pd(
                _mm256_and_pd(_mm256_cmp_pd::<_CMP_GT_OQ>(mz, zero), _mm256_cmp_pd::<_CMP_GE_OQ>(tc, zero)),
                _mm256_and_pd(
                    _mm256_and_pd(
                        _mm256_cmp_pd::<_CMP_GE_OQ>(tr, zero),
                        _mm256_cmp_pd::<_CMP_LE_OQ>(tc, c_max),
                    ),
                    _mm256_cmp_pd::<_CMP_LE_OQ>(tr, r_max),
                ),
            );
            let bits = _mm256_movemask_pd(ok);
            if bits == 0 {
                continue;
            }
            // Off-template lanes sample pixel (0, 0), then are dropped.
            let (tc, tr) = (_mm256_and_pd(tc, ok), _mm256_and_pd(tr, ok));
            // `as usize` truncates toward zero, as the conversion does here.
            let ic = _mm_min_epi32(_mm256_cvttpd_epi32(tc), ic_max);
            let ir = _mm_min_epi32(_mm256_cvttpd_epi32(tr), ir_max);
            let fc = _mm256_cvtpd_ps(_mm256_sub_pd(tc, _mm256_cvtepi32_pd(ic)));
            let fr = _mm256_cvtpd_ps(_mm256_sub_pd(tr, _mm256_cvtepi32_pd(ir)));
            let at = _mm_add_epi32(_mm_mullo_epi32(ir, _mm_set1_epi32(tw as i32)), ic);
            let mut idx = [0i32; 4];
            // SAFETY: `idx` is four i32 (16 bytes); unaligned store.
            unsafe { _mm_storeu_si128(idx.as_mut_ptr().cast::<__m128i>(), at) };
            let (mut a0, mut a1, mut b0, mut b1) = ([0f32; 4], [0f32; 4], [0f32; 4], [0f32; 4]);
            for l in 0..4 {
                // ic <= tw - 2 and ir <= th - 2: the 2x2 block is in the template.
                let i = idx[l] as usize;
                let (a, b) = (&t.pixels[i..i + 2], &t.pixels[i + tw..i + tw + 2]);
                (a0[l], a1[l], b0[l], b1[l]) = (a[0] as f32, a[1] as f32, b[0] as f32, b[1] as f32);
            }
            // SAFETY: four f32 each (16 bytes); unaligned loads.
            let [a0, a1, b0, b1] = [a0, a1, b0, b1].map(|v| unsafe { _mm_loadu_ps(v.as_ptr()) });
            let (gc, gr) = (_mm_sub_ps(one, fc), _mm_sub_ps(one, fr));
            let top = _mm_mul_ps(_mm_add_ps(_mm_mul_ps(a0, gc), _mm_mul_ps(a1, fc)), gr);
            let bottom = _mm_mul_ps(_mm_add_ps(_mm_mul_ps(b0, gc), _mm_mul_ps(b1, fc)), fr);
            let mut v = [0f32; 4];
            // SAFETY: `v` is four f32 (16 bytes); unaligned store.
            unsafe { _mm_storeu_ps(v.as_mut_ptr(), _mm_add_ps(top, bottom)) };
            for l in 0..4 {
                if bits & (1 << l) != 0 {
                    (data[k + l], mask[k + l]) = (v[l], true);
                }
            }
        }
        let k = 4 * chunks;
        super::scalar_row(t, h, &rays[k..], &mut data[k..], &mut mask[k..]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (xorshift).
    struct Rng(u64);
    impl Rng {
        fn f(&mut self) -> f64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// The row function (AVX2 where the CPU has it) gives the scalar
    /// sample's bits on every ray: inside, on the edges, off the template,
    /// behind the camera, NaN; rows of every length (remainders).
    #[test]
    fn row_matches_scalar_bit_for_bit() {
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        let (tw, th) = (37, 29);
        let pixels: Vec<u8> = (0..tw * th).map(|_| (rng.f() * 256.0) as u8).collect();
        let t = GreyTemplate { width: tw, height: th, pixels: &pixels };
        let mut checked = (0, 0);
        for trial in 0..400 {
            // A homography near a scaled identity, with some perspective.
            let s = 20.0 + 10.0 * rng.f();
            let h = [
                s * (1.0 + 0.2 * (rng.f() - 0.5)),
                s * 0.3 * (rng.f() - 0.5),
                18.0 + 4.0 * (rng.f() - 0.5),
                s * 0.3 * (rng.f() - 0.5),
                s * (1.0 + 0.2 * (rng.f() - 0.5)),
                14.0 + 4.0 * (rng.f() - 0.5),
                0.4 * (rng.f() - 0.5),
                0.4 * (rng.f() - 0.5),
                1.0 + if trial % 7 == 0 { -1.5 } else { 0.0 },
            ];
            let n = trial % 23 + 1;
            let mut rays: Vec<[f32; 2]> =
                (0..n).map(|_| [(1.6 * (rng.f() - 0.5)) as f32, (1.6 * (rng.f() - 0.5)) as f32]).collect();
            if trial % 5 == 0 {
                rays[0] = [f32::NAN, 0.0];
            }
            if trial % 3 == 0 {
                // Rays onto the last column and row exactly (all exact in
                // binary: column 16 * 1.125 + 18 = 36, row 16 * 0.875 + 14 = 28).
                let h1 = [16.0, 0.0, 18.0, 0.0, 16.0, 14.0, 0.0, 0.0, 1.0];
                let r = [1.125, 0.875];
                assert_eq!(homography_sample(&t, &h1, r), Some(pixels[tw * th - 1] as f32));
                let (mut d, mut m) = (vec![-1f32; 5], vec![false; 5]);
                homography_row(&t, &h1, &[r; 5], &mut d, &mut m);
                for k in 0..5 {
                    let want = homography_sample(&t, &h1, r);
                    assert_eq!(want.map(f32::to_bits), m[k].then(|| d[k].to_bits()));
                }
            }
            let (mut d, mut m) = (vec![-1f32; n], vec![false; n]);
            homography_row(&t, &h, &rays, &mut d, &mut m);
            for k in 0..n {
                match homography_sample(&t, &h, rays[k]) {
                    Some(v) => {
                        assert!(m[k], "trial {trial} ray {k}: sampled by the scalar code only");
                        assert_eq!(v.to_bits(), d[k].to_bits(), "trial {trial} ray {k}");
                        checked.0 += 1;
                    }
                    None => {
                        assert!(!m[k] && d[k] == -1.0, "trial {trial} ray {k}: sampled by the row only");
                        checked.1 += 1;
                    }
                }
            }
        }
        // Both kinds of ray were seen in numbers.
        assert!(checked.0 > 1000 && checked.1 > 500, "{checked:?}");
    }

    /// The bilinear sample against its definition, and its bounds.
    #[test]
    fn bilinear_interpolates_and_bounds() {
        let pixels = [0u8, 10, 20, 30, 40, 50];
        let t = GreyTemplate { width: 3, height: 2, pixels: &pixels };
        assert_eq!(bilinear(&t, 0.0, 0.0), Some(0.0));
        assert_eq!(bilinear(&t, 2.0, 1.0), Some(50.0));
        assert_eq!(bilinear(&t, 1.5, 0.5), Some(0.25 * (10.0 + 20.0 + 40.0 + 50.0)));
        assert_eq!(bilinear(&t, 2.0001, 0.0), None);
        assert_eq!(bilinear(&t, -1e-9, 0.0), None);
        assert_eq!(bilinear(&t, f64::NAN, 0.0), None);
    }
}

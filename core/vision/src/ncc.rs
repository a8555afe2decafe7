//! Normalized cross-correlation (NCC) of a landmark template over a search
//! window of the camera image, with a sub-pixel peak, an uncertainty and an
//! ambiguity test.
//!
//! # Conventions
//! Template pixel (i, j) has its centre at template coordinates (i, j); the
//! template centre is ((w-1)/2, (h-1)/2). Image pixel (0, 0) has its centre at
//! (0, 0). A template cut from the image with its top-left pixel at (x, y)
//! therefore matches at u = x + (w-1)/2, v = y + (h-1)/2.
//!
//! The NCC at a position is the Pearson correlation, over the template's valid
//! pixels, of the template and the image pixels under it (OpenCV's
//! `TM_CCOEFF_NORMED`, with a mask restricting both means and variances). It
//! is invariant to gain and offset of either. Where either side has (near)
//! zero variance the NCC is 0.
//!
//! # Approach
//! - The template is cropped to the bounding box of its valid pixels (warped
//!   templates have invalid corners: less work, and it may lie closer to the
//!   image border), zero-meaned over its valid pixels, and invalid pixels set
//!   to 0. As the coefficients sum to 0, the numerator is sum(t' * I) with no
//!   image mean to subtract.
//! - The search window of the image is copied once into a zero-padded buffer
//!   and centred by its own mean (keeps f32 sums exact enough for images with
//!   large offsets, e.g. 16-bit data).
//! - Numerator: a register-tiled direct correlation in f32 (16 positions x 4
//!   rows of accumulators per tile; per template coefficient, 2 window loads
//!   and 4 broadcasts feed 8 vector multiply-adds), compiled for AVX2+FMA
//!   (chosen at run time) and for the baseline target. At these sizes
//!   (32x32 template, 41x41 positions = 1.7M multiply-adds) it is faster than
//!   OpenCV's `matchTemplate` (which uses a DFT there); see `ncc_timing`.
//!   Each window row feeds only the columns where the template rows it
//!   meets have valid pixels (a rotated template's corners are skipped;
//!   their coefficients are 0, so every sum is what it was).
//! - Denominator: the image sums under the valid pixels, sum(m*I) and
//!   sum(m*I^2), in f64. Without a mask: separable running sums (the
//!   summed-area-table idea without the table): vertical over the template
//!   height, vectorised along x, then horizontal. With a mask: the mask is
//!   decomposed into rectangles (maximal vertical stacks of identical row
//!   runs of valid pixels), each summed per position from row prefix sums
//!   (one-row rectangles) or a summed-area table (taller ones), vectorised
//!   along x. Exact for any mask, holes included.
//! - Buffers are kept per thread between calls; no threads are spawned (run
//!   landmarks in parallel from the caller).
//! - Peak: arg max; sub-pixel offset from a 2D quadratic (Taylor expansion
//!   with central differences) on the 3x3 neighbourhood, falling back to
//!   separable parabolas where the Hessian is not negative definite.
//! - Ambiguity: the second peak is the best NCC outside the main lobe, which
//!   is the region flooded downhill (8-connected, non-increasing) from the
//!   peak plus a disk of radius [`LOBE_MIN_RADIUS`] around it (so noise
//!   ripples on the lobe's flanks do not count).

/// Radius (px) of the disk around the peak always counted in the main lobe.
pub const LOBE_MIN_RADIUS: f64 = 2.0;

/// Output tile: positions along x (two 8-lane vectors) and rows.
const TX: usize = 16;
const TY: usize = 4;

/// A grey image borrowed row-major (f32, any range), e.g. the camera frame.
#[derive(Clone, Copy, Debug)]
pub struct ImageView<'a> {
    pub width: usize,
    pub height: usize,
    pub data: &'a [f32],
}

impl<'a> ImageView<'a> {
    /// Panics if `data.len() != width * height`.
    pub fn new(width: usize, height: usize, data: &'a [f32]) -> Self {
        assert_eq!(data.len(), width * height, "image data size");
        ImageView { width, height, data }
    }
}

/// A template with an optional validity mask (warped templates have invalid
/// corners), row-major.
#[derive(Clone, Debug)]
pub struct Template {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
    /// `true` = valid pixel; `None` = all valid.
    pub mask: Option<Vec<bool>>,
}

impl Template {
    /// Panics if `data.len() != width * height` (or the mask's length differs).
    pub fn new(width: usize, height: usize, data: Vec<f32>, mask: Option<Vec<bool>>) -> Self {
        assert_eq!(data.len(), width * height, "template data size");
        if let Some(m) = &mask {
            assert_eq!(m.len(), width * height, "template mask size");
        }
        Template { width, height, data, mask }
    }

    /// Template centre in template pixel coordinates.
    pub fn centre(&self) -> (f64, f64) {
        ((self.width as f64 - 1.0) / 2.0, (self.height as f64 - 1.0) / 2.0)
    }
}

/// Acceptance thresholds of [`match_template`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NccParams {
    /// Minimum NCC of the peak (e.g. 0.6).
    pub min_peak: f32,
    /// Maximum ratio second / peak, the second peak being the best NCC outside
    /// the main lobe (e.g. 0.9).
    pub max_second_ratio: f32,
    /// Minimum standard deviation of the template over its valid pixels, in
    /// image units (set it near the image noise level).
    pub min_template_std: f32,
}

impl Default for NccParams {
    fn default() -> Self {
        NccParams { min_peak: 0.6, max_second_ratio: 0.9, min_template_std: 1e-3 }
    }
}

/// An accepted match.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NccMatch {
    /// Template centre position in image pixels (u, v), sub-pixel.
    pub u: f64,
    pub v: f64,
    /// NCC at the best integer position.
    pub peak: f32,
    /// Best NCC outside the main lobe (-1 if the search area has none).
    pub second: f32,
    /// 1-sigma position uncertainty (px) along the flattest direction of the
    /// peak, sqrt((1 - peak) / (peak * n * c)) with n the valid template
    /// pixels and c the smallest curvature of the NCC surface (1/px^2): the
    /// least-squares matching bound reading 1 - peak as the noise-to-signal
    /// variance ratio (1 - peak floored at 1e-3). Infinite where the peak is
    /// not curved both ways (an edge).
    pub sigma_px: f64,
}

/// Why [`match_template`] found no match (in the order they are tested).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum NccReject {
    /// The template's standard deviation is below `min_template_std`.
    TooFlat,
    /// Fewer than 3x3 search positions have the template inside the image.
    OutOfImage,
    /// The best NCC is below `min_peak`.
    WeakPeak { peak: f32 },
    /// The second peak is above `max_second_ratio * peak`.
    Ambiguous { peak: f32, second: f32 },
    /// The best position is on the border of the (clipped) search area: the
    /// true peak may lie outside.
    PeakOnBorder,
}

/// Search the template centred on predicted (u0, v0) within ±radius px.
///
/// The searched positions are the integer template placements whose top-left
/// is round(u0 - (w-1)/2) ± radius (same for v), clipped to the placements
/// where the template's valid pixels lie inside the image.
pub fn match_template(
    image: &ImageView,
    tpl: &Template,
    u0: f64,
    v0: f64,
    radius: usize,
    params: &NccParams,
) -> Result<NccMatch, NccReject> {
    let prep = Prepared::new(tpl).ok_or(NccReject::TooFlat)?;
    if prep.std.is_nan() || prep.std <= params.min_template_std as f64 {
        return Err(NccReject::TooFlat);
    }
    let (cx, cy) = tpl.centre();
    let (fx, fy) = (u0 - cx, v0 - cy);
    let lim = 1e15;
    if !(fx.abs() < lim && fy.abs() < lim) {
        return Err(NccReject::OutOfImage);
    }
    let r = radius as isize;
    let (xc, yc) = (fx.round() as isize, fy.round() as isize);
    // Placements with the valid box inside the image.
    let (xmin, xmax) = (-(prep.ox as isize), image.width as isize - (prep.ox + prep.w) as isize);
    let (ymin, ymax) = (-(prep.oy as isize), image.height as isize - (prep.oy + prep.h) as isize);
    let (x0, x1) = ((xc - r).max(xmin), (xc + r).min(xmax));
    let (y0, y1) = ((yc - r).max(ymin), (yc + r).min(ymax));
    if x1 - x0 < 2 || y1 - y0 < 2 {
        return Err(NccReject::OutOfImage);
    }
    let (nx, ny) = ((x1 - x0 + 1) as usize, (y1 - y0 + 1) as usize);
    let mut s = prep.surface(image, x0, y0, nx, ny);

    // The first maximum (its value over the whole surface first: a pass
    // without a branch a position).
    let best = s.iter().fold(f32::NEG_INFINITY, |a, &v| a.max(v));
    if !(best >= params.min_peak) {
        return Err(NccReject::WeakPeak { peak: best });
    }
    let bi = s.iter().position(|&v| v == best).expect("the maximum is on the surface");
    let (bx, by) = (bi % nx, bi / nx);
    let on_border = bx == 0 || by == 0 || bx == nx - 1 || by == ny - 1;
    // The peak's 3x3 neighbourhood, before the second peak's search marks its lobe.
    let mut around = [[0f64; 3]; 3];
    if !on_border {
        for (j, row) in around.iter_mut().enumerate() {
            for (i, v) in row.iter_mut().enumerate() {
                *v = s[(by + j - 1) * nx + bx + i - 1] as f64;
            }
        }
    }
    let second = second_peak(&mut s, nx, ny, bx, by);
    if second > params.max_second_ratio * best {
        return Err(NccReject::Ambiguous { peak: best, second });
    }
    if on_border {
        return Err(NccReject::PeakOnBorder);
    }
    let f = |dx: isize, dy: isize| around[(1 + dy) as usize][(1 + dx) as usize];
    let (du, dv, sigma_px) = subpixel(f, best as f64, prep.n);
    Ok(NccMatch {
        u: (x0 + bx as isize) as f64 + cx + du,
        v: (y0 + by as isize) as f64 + cy + dv,
        peak: best,
        second,
        sigma_px,
    })
}

/// The full NCC surface (for tests and debugging): `nx * ny` values, row-major,
/// element (i, j) for the template's top-left pixel at image (x0 + i, y0 + j),
/// i.e. centre u = x0 + i + (w-1)/2. NaN where the template's valid pixels do
/// not all lie inside the image; 0 where either side is flat.
pub fn ncc_surface(
    image: &ImageView,
    tpl: &Template,
    x0: isize,
    y0: isize,
    nx: usize,
    ny: usize,
) -> Vec<f32> {
    let mut out = vec![f32::NAN; nx * ny];
    let Some(prep) = Prepared::new(tpl) else {
        return out;
    };
    let (xmin, xmax) = (-(prep.ox as isize), image.width as isize - (prep.ox + prep.w) as isize);
    let (ymin, ymax) = (-(prep.oy as isize), image.height as isize - (prep.oy + prep.h) as isize);
    let (cx0, cx1) = (x0.max(xmin), (x0 + nx as isize - 1).min(xmax));
    let (cy0, cy1) = (y0.max(ymin), (y0 + ny as isize - 1).min(ymax));
    if cx1 < cx0 || cy1 < cy0 {
        return out;
    }
    let (cnx, cny) = ((cx1 - cx0 + 1) as usize, (cy1 - cy0 + 1) as usize);
    let s = prep.surface(image, cx0, cy0, cnx, cny);
    for j in 0..cny {
        let o = (cy0 - y0) as usize + j;
        let d = (cx0 - x0) as usize;
        out[o * nx + d..o * nx + d + cnx].copy_from_slice(&s[j * cnx..(j + 1) * cnx]);
    }
    out
}

/// A template cropped to its valid box, zero-meaned, with its mask as
/// rectangles.
struct Prepared {
    /// Crop offset in the original template, and crop size.
    ox: usize,
    oy: usize,
    w: usize,
    h: usize,
    /// Zero-mean coefficients (0 where invalid), with TY-1 zero rows above and
    /// below for the tiled kernel.
    coef: Vec<f32>,
    /// sqrt(sum t'^2), infinite for a flat template (NCC 0).
    norm: f64,
    /// Standard deviation over the valid pixels.
    std: f64,
    n: f64,
    /// Valid pixels as rectangles (x0, x1, y0, y1), half-open, crop coordinates.
    rects: Vec<(usize, usize, usize, usize)>,
    /// Per window row `k` of a tile (`0..h + TY - 1`), the crop columns
    /// `[lo, hi)` holding the valid pixels of the template rows it feeds
    /// (`k - TY + 1..=k`): the correlation skips the taps outside, whose
    /// coefficients are 0 (a warped template's corners).
    taps: Vec<(usize, usize)>,
}

impl Prepared {
    /// None if no pixel is valid.
    fn new(tpl: &Template) -> Option<Prepared> {
        let (tw, th) = (tpl.width, tpl.height);
        assert_eq!(tpl.data.len(), tw * th, "template data size");
        let mask = tpl.mask.as_deref();
        // Valid box.
        let (mut x0, mut x1, mut y0, mut y1) = (0, tw, 0, th);
        if let Some(m) = mask {
            assert_eq!(m.len(), tw * th, "template mask size");
            (x0, x1, y0, y1) = (usize::MAX, 0, usize::MAX, 0);
            for (j, row) in m.chunks_exact(tw.max(1)).enumerate() {
                if let (Some(a), Some(b)) = (row.iter().position(|&v| v), row.iter().rposition(|&v| v)) {
                    (x0, x1, y0, y1) = (x0.min(a), x1.max(b + 1), y0.min(j), y1.max(j + 1));
                }
            }
        }
        if x1 <= x0 || y1 <= y0 {
            return None;
        }
        let (w, h) = (x1 - x0, y1 - y0);
        // The crop's rows of data and of validity (all valid without a mask).
        let data_row = |j: usize| &tpl.data[(y0 + j) * tw + x0..][..w];
        let all_valid = if mask.is_none() { vec![true; w] } else { Vec::new() };
        let mask_row = |j: usize| mask.map_or(&all_valid[..], |m| &m[(y0 + j) * tw + x0..][..w]);
        // Sums in row-major order, one pixel at a time.
        let (mut n, mut sum) = (0usize, 0f64);
        for j in 0..h {
            match mask {
                None => sum += data_row(j).iter().map(|&v| v as f64).sum::<f64>(),
                Some(_) => {
                    for (&v, &m) in data_row(j).iter().zip(mask_row(j)) {
                        if m {
                            sum += v as f64;
                            n += 1;
                        }
                    }
                }
            }
        }
        if mask.is_none() {
            n = w * h;
        }
        let mean = sum / n as f64;
        let pad = TY - 1;
        let mut coef = vec![0f32; (h + 2 * pad) * w];
        let mut ss = 0f64;
        for j in 0..h {
            for ((c, &v), &m) in coef[(j + pad) * w..][..w].iter_mut().zip(data_row(j)).zip(mask_row(j)) {
                if m {
                    let d = v as f64 - mean;
                    *c = d as f32;
                    ss += d * d;
                }
            }
        }
        // Row runs, merged into rectangles when identical on consecutive rows.
        let mut rects: Vec<(usize, usize, usize, usize)> = Vec::new();
        if mask.is_none() {
            rects.push((0, w, 0, h));
        } else {
            let (mut open, mut next) = (Vec::new(), Vec::new()); // rects ending on the previous row
            for j in 0..h {
                next.clear();
                let row = mask_row(j);
                let mut i = 0;
                while i < w {
                    if !row[i] {
                        i += 1;
                        continue;
                    }
                    let a = i;
                    while i < w && row[i] {
                        i += 1;
                    }
                    match open.iter().find(|&&k: &&usize| rects[k].0 == a && rects[k].1 == i) {
                        Some(&k) => {
                            rects[k].3 = j + 1;
                            next.push(k);
                        }
                        None => {
                            rects.push((a, i, j, j + 1));
                            next.push(rects.len() - 1);
                        }
                    }
                }
                std::mem::swap(&mut open, &mut next);
            }
        }
        // Each crop row's span of valid pixels (empty: (w, 0)), then their
        // unions over the TY rows each window row feeds.
        let spans: Vec<(usize, usize)> = (0..h)
            .map(|j| {
                let row = mask_row(j);
                match (row.iter().position(|&v| v), row.iter().rposition(|&v| v)) {
                    (Some(lo), Some(hi)) => (lo, hi + 1),
                    _ => (w, 0),
                }
            })
            .collect();
        let taps: Vec<(usize, usize)> = (0..h + TY - 1)
            .map(|k| {
                (k.saturating_sub(TY - 1)..(k + 1).min(h))
                    .fold((w, 0), |(lo, hi), j| (lo.min(spans[j].0), hi.max(spans[j].1)))
            })
            .collect();
        Some(Prepared {
            ox: x0,
            oy: y0,
            w,
            h,
            coef,
            norm: if ss > 0.0 { ss.sqrt() } else { f64::INFINITY },
            std: (ss / n as f64).sqrt(),
            n: n as f64,
            rects,
            taps,
        })
    }

    /// NCC at crop placements whose original top-left is (x0 + i, y0 + j); all
    /// of them must have the crop inside the image.
    fn surface(&self, image: &ImageView, x0: isize, y0: isize, nx: usize, ny: usize) -> Vec<f32> {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { self.surface_avx2(image, x0, y0, nx, ny) };
        }
        self.surface_impl::<false>(image, x0, y0, nx, ny)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn surface_avx2(&self, image: &ImageView, x0: isize, y0: isize, nx: usize, ny: usize) -> Vec<f32> {
        self.surface_impl::<true>(image, x0, y0, nx, ny)
    }

    /// `FMA`: compiled for AVX2 + FMA.
    #[inline(always)]
    fn surface_impl<const FMA: bool>(
        &self,
        image: &ImageView,
        x0: isize,
        y0: isize,
        nx: usize,
        ny: usize,
    ) -> Vec<f32> {
        assert_eq!(image.data.len(), image.width * image.height, "image data size");
        let (bx, by) = ((x0 + self.ox as isize) as usize, (y0 + self.oy as isize) as usize);
        assert!(bx + nx + self.w - 1 <= image.width && by + ny + self.h - 1 <= image.height);
        let mut sc = SCRATCH.take();
        let nxp = nx.div_ceil(TX) * TX;
        let nyp = ny.div_ceil(TY) * TY;
        // Window, centred by its (approximate) mean, zero-padded to the tiled size.
        let (ww, wh) = (nx + self.w - 1, ny + self.h - 1);
        let (wp, hp) = (nxp + self.w - 1, nyp + self.h - 1);
        let mut lanes = [0f32; 8];
        for y in 0..wh {
            let row = &image.data[(by + y) * image.width + bx..][..ww];
            let mut part = [0f32; 8];
            for c in row.chunks_exact(8) {
                for l in 0..8 {
                    part[l] += c[l];
                }
            }
            for (l, &v) in row.chunks_exact(8).remainder().iter().enumerate() {
                part[l] += v;
            }
            for l in 0..8 {
                lanes[l] += part[l];
            }
        }
        let mean = lanes.iter().map(|&v| v as f64).sum::<f64>() / (ww * wh) as f64;
        let mean = if mean.is_finite() { mean as f32 } else { 0.0 };
        let win = zeroed(&mut sc.win, wp * hp);
        for y in 0..wh {
            let row = &image.data[(by + y) * image.width + bx..][..ww];
            for (d, &v) in win[y * wp..y * wp + ww].iter_mut().zip(row) {
                *d = v - mean;
            }
        }
        // (Every element is written by the kernel: no need to zero it.)
        if sc.num.len() < nxp * nyp {
            sc.num.resize(nxp * nyp, 0.0);
        }
        let num = &mut sc.num[..nxp * nyp];
        if FMA {
            // SAFETY: FMA is only true in `surface_avx2`, called after detection.
            #[cfg(target_arch = "x86_64")]
            unsafe {
                correlate_avx2(win, wp, &self.coef, &self.taps, self.w, self.h, num, nxp, nyp)
            };
        } else {
            correlate_tiles::<false>(win, wp, &self.coef, &self.taps, self.w, self.h, num, nxp, nyp);
        }

        // Image sums under the valid pixels, sum(m*I) and sum(m*I^2), in f64.
        // No mask (a single rectangle): separable running sums, vertical over
        // the template height (vectorised along x), then horizontal. Mask: row
        // prefix sums, rp[y * sw + x] = sum over [0, x) of row y, for the
        // one-row rectangles, and SATs from them, sat[y * sw + x] = sum over
        // [0, x) x [0, y), for the taller ones.
        let full = self.rects.len() == 1;
        let sw = ww + 1;
        let [rp1, rp2] = &mut sc.rp;
        let [sat1, sat2] = &mut sc.sat;
        let (rp1, rp2) =
            if full { (&mut [][..], &mut [][..]) } else { (zeroed(rp1, sw * wh), zeroed(rp2, sw * wh)) };
        if !full {
            // Four rows at a time: independent dependency chains.
            for y0 in (0..wh).step_by(4) {
                let rows = (wh - y0).min(4);
                let (mut r1, mut r2) = ([0f64; 4], [0f64; 4]);
                for x in 0..ww {
                    for q in 0..rows {
                        let v = win[(y0 + q) * wp + x] as f64;
                        r1[q] += v;
                        r2[q] += v * v;
                        rp1[(y0 + q) * sw + x + 1] = r1[q];
                        rp2[(y0 + q) * sw + x + 1] = r2[q];
                    }
                }
            }
        }
        let (sat1, sat2) = if full {
            // Column sums over the first template-high band.
            let (v1, v2) = (zeroed(sat1, ww), zeroed(sat2, ww));
            for j in 0..self.h {
                for ((a, b), &v) in v1.iter_mut().zip(v2.iter_mut()).zip(&win[j * wp..][..ww]) {
                    let v = v as f64;
                    *a += v;
                    *b += v * v;
                }
            }
            (v1, v2)
        } else if self.rects.iter().any(|r| r.3 > r.2 + 1) {
            let (sat1, sat2) = (zeroed(sat1, sw * (wh + 1)), zeroed(sat2, sw * (wh + 1)));
            for y in 0..wh {
                let (t, u) = (y * sw, (y + 1) * sw);
                for x in 0..sw {
                    sat1[u + x] = sat1[t + x] + rp1[t + x];
                    sat2[u + x] = sat2[t + x] + rp2[t + x];
                }
            }
            (sat1, sat2)
        } else {
            (&mut [][..], &mut [][..])
        };
        let [m1, m2] = &mut sc.m;
        let (m1, m2) = (zeroed(m1, nx), zeroed(m2, nx));
        let mut out = vec![0f32; nx * ny];
        let inv_n = 1.0 / self.n;
        let w = self.w;
        for y in 0..ny {
            if full {
                let (mut a, mut b) = (sat1[..w].iter().sum::<f64>(), sat2[..w].iter().sum::<f64>());
                (m1[0], m2[0]) = (a, b);
                for x in 1..nx {
                    a += sat1[x + w - 1] - sat1[x - 1];
                    b += sat2[x + w - 1] - sat2[x - 1];
                    (m1[x], m2[x]) = (a, b);
                }
                if y + 1 < ny {
                    let (new, old) = (&win[(y + self.h) * wp..][..ww], &win[y * wp..][..ww]);
                    for x in 0..ww {
                        let (n, o) = (new[x] as f64, old[x] as f64);
                        sat1[x] += n - o;
                        sat2[x] += n * n - o * o;
                    }
                }
            } else {
                m1.fill(0.0);
                m2.fill(0.0);
                for &(a, b, c, d) in &self.rects {
                    let (t, u) = ((y + c) * sw, (y + d) * sw);
                    if d == c + 1 {
                        let (pa, pb) = (&rp1[t + a..][..nx], &rp1[t + b..][..nx]);
                        let (qa, qb) = (&rp2[t + a..][..nx], &rp2[t + b..][..nx]);
                        for x in 0..nx {
                            m1[x] += pb[x] - pa[x];
                            m2[x] += qb[x] - qa[x];
                        }
                    } else {
                        box_sum(m1, sat1, t, u, a, b);
                        box_sum(m2, sat2, t, u, a, b);
                    }
                }
            }
            let nrow = &num[y * nxp..][..nx];
            for (x, o) in out[y * nx..][..nx].iter_mut().enumerate() {
                let var = m2[x] - m1[x] * m1[x] * inv_n;
                // Flat image (or template): den = inf, NCC 0.
                let den = if var > 1e-6 * m2[x] { var.sqrt() * self.norm } else { f64::INFINITY };
                *o = (nrow[x] as f64 / den).clamp(-1.0, 1.0) as f32;
            }
        }
        SCRATCH.set(sc);
        out
    }
}

/// Per-thread buffers of [`Prepared::surface`], kept between calls.
#[derive(Default)]
struct Scratch {
    win: Vec<f32>,
    num: Vec<f32>,
    rp: [Vec<f64>; 2],
    sat: [Vec<f64>; 2],
    m: [Vec<f64>; 2],
}

thread_local! {
    static SCRATCH: std::cell::Cell<Scratch> = std::cell::Cell::new(Scratch::default());
}

/// `v` resized to `n` zeros.
#[inline(always)]
fn zeroed<T: Copy + Default>(v: &mut Vec<T>, n: usize) -> &mut [T] {
    v.clear();
    v.resize(n, T::default());
    v
}

/// acc[x] += box [x+a, x+b) x rows [t, u) / sw of a SAT, for x in 0..acc.len().
#[inline(always)]
fn box_sum(acc: &mut [f64], sat: &[f64], t: usize, u: usize, a: usize, b: usize) {
    let n = acc.len();
    let (ta, tb) = (&sat[t + a..][..n], &sat[t + b..][..n]);
    let (ua, ub) = (&sat[u + a..][..n], &sat[u + b..][..n]);
    for x in 0..n {
        acc[x] += ub[x] - ua[x] - tb[x] + ta[x];
    }
}

/// [`correlate_tiles`] for AVX2 + FMA, kept out of line (better register allocation).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline(never)]
#[allow(clippy::too_many_arguments)]
fn correlate_avx2(
    win: &[f32],
    wp: usize,
    coef: &[f32],
    taps: &[(usize, usize)],
    tw: usize,
    th: usize,
    num: &mut [f32],
    nxp: usize,
    nyp: usize,
) {
    correlate_tiles::<true>(win, wp, coef, taps, tw, th, num, nxp, nyp);
}

/// num[y * nxp + x] = sum_{j,i} coef[(j + TY-1) * tw + i] * win[(y + j) * wp + x + i].
/// Register-tiled: TY output rows x TX positions of accumulators;
/// window row y+k feeds output row y+r through template row k-r (padded rows
/// of `coef` are zero), so each window load serves TY rows. Window row `k`
/// feeds only its columns `taps[k]` (the others' coefficients are 0: skipping
/// them leaves every sum as it was, term for term).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_tiles<const FMA: bool>(
    win: &[f32],
    wp: usize,
    coef: &[f32],
    taps: &[(usize, usize)],
    tw: usize,
    th: usize,
    num: &mut [f32],
    nxp: usize,
    nyp: usize,
) {
    assert!(nxp % TX + nyp % TY == 0 && wp >= nxp + tw - 1);
    assert!(taps.len() == th + TY - 1 && taps.iter().all(|&(lo, hi)| lo >= hi || hi <= tw));
    assert!(win.len() >= (nyp + th - 1) * wp && coef.len() == (th + 2 * (TY - 1)) * tw);
    assert!(num.len() >= nxp * nyp);
    for y in (0..nyp).step_by(TY) {
        for x in (0..nxp).step_by(TX) {
            let mut acc = [[0f32; TX]; TY];
            for (k, &(lo, hi)) in taps.iter().enumerate() {
                let row = &win[(y + k) * wp + x..][..tw + TX - 1];
                let trows: [&[f32]; TY] = std::array::from_fn(|r| &coef[(k + TY - 1 - r) * tw..][..tw]);
                for i in lo..hi {
                    let v: &[f32; TX] = row[i..i + TX].try_into().unwrap();
                    for r in 0..TY {
                        let c = trows[r][i];
                        for l in 0..TX {
                            acc[r][l] = if FMA { c.mul_add(v[l], acc[r][l]) } else { acc[r][l] + c * v[l] };
                        }
                    }
                }
            }
            for (r, a) in acc.iter().enumerate() {
                num[(y + r) * nxp + x..][..TX].copy_from_slice(a);
            }
        }
    }
}

/// Best surface value outside the main lobe of the peak at (bx, by): the
/// region flooded downhill from it plus a disk of radius LOBE_MIN_RADIUS.
/// The lobe's values are overwritten (NaN) in `s`.
fn second_peak(s: &mut [f32], nx: usize, ny: usize, bx: usize, by: usize) -> f32 {
    // Flooded pixels are marked NaN: `w <= v` is then false, and `max` skips them.
    let mut stack = vec![(bx, by, s[by * nx + bx])];
    s[by * nx + bx] = f32::NAN;
    while let Some((x, y, v)) = stack.pop() {
        for j in y.saturating_sub(1)..(y + 2).min(ny) {
            for i in x.saturating_sub(1)..(x + 2).min(nx) {
                let w = s[j * nx + i];
                if w <= v {
                    s[j * nx + i] = f32::NAN;
                    stack.push((i, j, w));
                }
            }
        }
    }
    let r = LOBE_MIN_RADIUS as isize;
    for y in (by as isize - r).max(0)..=(by as isize + r).min(ny as isize - 1) {
        for x in (bx as isize - r).max(0)..=(bx as isize + r).min(nx as isize - 1) {
            let (dx, dy) = ((x - bx as isize) as f64, (y - by as isize) as f64);
            if dx * dx + dy * dy <= LOBE_MIN_RADIUS * LOBE_MIN_RADIUS {
                s[y as usize * nx + x as usize] = f32::NAN;
            }
        }
    }
    s.iter().fold(-1f32, |a, &v| a.max(v))
}

/// Sub-pixel offset (du, dv) and sigma from the 3x3 neighbourhood `f` of a
/// maximum with value `f(0, 0)`, `n` valid template pixels.
fn subpixel(f: impl Fn(isize, isize) -> f64, peak: f64, n: f64) -> (f64, f64, f64) {
    let c = f(0, 0);
    let gx = (f(1, 0) - f(-1, 0)) / 2.0;
    let gy = (f(0, 1) - f(0, -1)) / 2.0;
    let hxx = f(1, 0) + f(-1, 0) - 2.0 * c;
    let hyy = f(0, 1) + f(0, -1) - 2.0 * c;
    let hxy = (f(1, 1) - f(1, -1) - f(-1, 1) + f(-1, -1)) / 4.0;
    let det = hxx * hyy - hxy * hxy;
    let parabola = |g: f64, h: f64| if h < 0.0 { (-g / h).clamp(-0.5, 0.5) } else { 0.0 };
    let (mut du, mut dv) = (parabola(gx, hxx), parabola(gy, hyy));
    let mut sigma = f64::INFINITY;
    if hxx < 0.0 && det > 0.0 {
        let (ux, uy) = (-(hyy * gx - hxy * gy) / det, -(hxx * gy - hxy * gx) / det);
        if ux.abs() <= 1.0 && uy.abs() <= 1.0 {
            (du, dv) = (ux, uy);
        }
        // Smallest curvature: smallest eigenvalue of -H.
        let (tr, d) = (-(hxx + hyy), ((hxx - hyy).powi(2) + 4.0 * hxy * hxy).sqrt());
        let lmin = (tr - d) / 2.0;
        if lmin > 0.0 {
            sigma = ((1.0 - peak).max(1e-3) / (peak.max(1e-3) * n * lmin)).sqrt();
        }
    }
    (du, dv, sigma)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// xorshift64* in [0, 1).
    struct Rng(u64);
    impl Rng {
        fn f(&mut self) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    fn noise(rng: &mut Rng, n: usize) -> Vec<f32> {
        (0..n).map(|_| rng.f() as f32).collect()
    }

    /// Band-limited random texture: a sum of sinusoids, exact at any shift.
    struct Texture(Vec<(f64, f64, f64, f64)>);
    impl Texture {
        fn new(rng: &mut Rng, n: usize, kmax: f64) -> Self {
            Texture(
                (0..n)
                    .map(|_| {
                        let (k, a) = (kmax * (0.15 + 0.85 * rng.f()), 2.0 * std::f64::consts::PI * rng.f());
                        (k * a.cos(), k * a.sin(), 2.0 * std::f64::consts::PI * rng.f(), 0.5 + rng.f())
                    })
                    .collect(),
            )
        }
        fn at(&self, x: f64, y: f64) -> f64 {
            self.0.iter().map(|&(kx, ky, p, a)| a * (kx * x + ky * y + p).cos()).sum()
        }
        fn image(&self, w: usize, h: usize, sx: f64, sy: f64) -> Vec<f32> {
            (0..w * h).map(|k| self.at((k % w) as f64 - sx, (k / w) as f64 - sy) as f32).collect()
        }
    }

    fn cut(img: &[f32], iw: usize, x: usize, y: usize, w: usize, h: usize) -> Vec<f32> {
        (0..h).flat_map(|j| img[(y + j) * iw + x..][..w].to_vec()).collect()
    }

    /// Naive f64 NCC; NaN where the valid pixels leave the image.
    fn brute(img: &ImageView, tpl: &Template, x0: isize, y0: isize, nx: usize, ny: usize) -> Vec<f32> {
        let (w, h) = (tpl.width, tpl.height);
        let valid = |i: usize, j: usize| tpl.mask.as_ref().is_none_or(|m| m[j * w + i]);
        let mut out = vec![f32::NAN; nx * ny];
        for py in 0..ny {
            'pos: for px in 0..nx {
                let (mut st, mut si, mut n) = (0f64, 0f64, 0f64);
                for j in 0..h {
                    for i in 0..w {
                        if valid(i, j) {
                            let (x, y) = (x0 + (px + i) as isize, y0 + (py + j) as isize);
                            if x < 0 || y < 0 || x >= img.width as isize || y >= img.height as isize {
                                continue 'pos;
                            }
                            st += tpl.data[j * w + i] as f64;
                            si += img.data[y as usize * img.width + x as usize] as f64;
                            n += 1.0;
                        }
                    }
                }
                let (mt, mi) = (st / n, si / n);
                let (mut stt, mut sii, mut sti) = (0f64, 0f64, 0f64);
                for j in 0..h {
                    for i in 0..w {
                        if valid(i, j) {
                            let (x, y) =
                                ((x0 + (px + i) as isize) as usize, (y0 + (py + j) as isize) as usize);
                            let t = tpl.data[j * w + i] as f64 - mt;
                            let v = img.data[y * img.width + x] as f64 - mi;
                            (stt, sii, sti) = (stt + t * t, sii + v * v, sti + t * v);
                        }
                    }
                }
                out[py * nx + px] = (sti / (stt * sii).sqrt()) as f32;
            }
        }
        out
    }

    fn assert_close(a: &[f32], b: &[f32], tol: f32) {
        assert_eq!(a.len(), b.len());
        for (k, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x.is_nan() && y.is_nan()) || (x - y).abs() <= tol,
                "element {k}: {x} vs {y} (diff {})",
                (x - y).abs()
            );
        }
    }

    /// A warped-looking mask: valid inside a rotated square, plus some holes.
    fn diamond_mask(rng: &mut Rng, w: usize, h: usize, holes: f64) -> Vec<bool> {
        let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        (0..w * h)
            .map(|k| {
                let (x, y) = ((k % w) as f64 - cx, (k / w) as f64 - cy);
                (x + 0.4 * y).abs() + (y - 0.3 * x).abs() < 0.75 * w as f64 && rng.f() >= holes
            })
            .collect()
    }

    #[test]
    fn ncc_surface_matches_brute_force() {
        let mut rng = Rng(0x1234_5678_9abc_def1);
        for case in 0..12 {
            let (iw, ih) = (40 + case * 3, 35 + case * 2);
            // Offset and gain so that cancellation would show.
            let img: Vec<f32> = noise(&mut rng, iw * ih).iter().map(|v| 500.0 + 40.0 * v).collect();
            let (w, h) = (3 + case * 2, 4 + (case * 5) % 17);
            let data = noise(&mut rng, w * h);
            let mask = (case % 2 == 1).then(|| diamond_mask(&mut rng, w, h, 0.05));
            let img = ImageView::new(iw, ih, &img);
            let tpl = Template::new(w, h, data, mask);
            // Partly outside the image on purpose (NaN there).
            let (x0, y0, nx, ny) = (-3, -2, iw - w + 5, ih - h + 4 - case % 3);
            let got = ncc_surface(&img, &tpl, x0, y0, nx, ny);
            let want = brute(&img, &tpl, x0, y0, nx, ny);
            assert!(want.iter().filter(|v| v.is_finite()).count() > nx * ny / 2);
            assert_close(&got, &want, 1e-4);
        }
    }

    #[test]
    fn ncc_gain_offset_invariance() {
        let mut rng = Rng(99);
        let (iw, ih, w, h) = (60, 50, 17, 13);
        let img = noise(&mut rng, iw * ih);
        let img2: Vec<f32> = img.iter().map(|v| 3.7 * v + 1000.0).collect();
        let data = noise(&mut rng, w * h);
        let data2: Vec<f32> = data.iter().map(|v| 0.2 * v - 7.0).collect();
        let mask = Some(diamond_mask(&mut rng, w, h, 0.05));
        let a = ncc_surface(
            &ImageView::new(iw, ih, &img),
            &Template::new(w, h, data, mask.clone()),
            0,
            0,
            40,
            30,
        );
        let b = ncc_surface(&ImageView::new(iw, ih, &img2), &Template::new(w, h, data2, mask), 0, 0, 40, 30);
        assert!(a.iter().all(|v| v.is_finite()));
        assert_close(&a, &b, 1e-4);
    }

    #[test]
    fn ncc_subpixel_shift_found() {
        let mut rng = Rng(7);
        let params = NccParams::default();
        let (iw, ih, w, h) = (120, 110, 32, 32);
        let tex = Texture::new(&mut rng, 60, 0.9);
        let base = tex.image(iw, ih, 0.0, 0.0);
        let (tx, ty) = (44, 38);
        let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let mut worst = 0f64;
        for k in 0..12 {
            let (sx, sy) = (-3.0 + 0.53 * k as f64, 2.4 - 0.41 * k as f64);
            let shifted = tex.image(iw, ih, sx, sy);
            for masked in [false, true] {
                let mask = masked.then(|| diamond_mask(&mut rng, w, h, 0.05));
                let tpl = Template::new(w, h, cut(&base, iw, tx, ty, w, h), mask);
                let m = match_template(
                    &ImageView::new(iw, ih, &shifted),
                    &tpl,
                    tx as f64 + cx + 1.7,
                    ty as f64 + cy - 2.2,
                    10,
                    &params,
                )
                .unwrap();
                let (eu, ev) = (m.u - (tx as f64 + cx + sx), m.v - (ty as f64 + cy + sy));
                worst = worst.max(eu.abs()).max(ev.abs());
                assert!(
                    m.peak > 0.95 && m.sigma_px > 1e-3 && m.sigma_px < 0.1 && m.second < 0.9 * m.peak,
                    "{m:?}"
                );
            }
        }
        assert!(worst < 0.05, "worst error {worst} px");
    }

    #[test]
    fn ncc_integer_cut_exact() {
        let mut rng = Rng(11);
        let (iw, ih, w, h) = (90, 80, 31, 24);
        let img = Texture::new(&mut rng, 40, 1.0).image(iw, ih, 0.0, 0.0);
        let tpl = Template::new(w, h, cut(&img, iw, 30, 25, w, h), None);
        let m = match_template(&ImageView::new(iw, ih, &img), &tpl, 48.0, 33.0, 8, &NccParams::default())
            .unwrap();
        assert!((m.u - 45.0).abs() < 0.02 && (m.v - 36.5).abs() < 0.02, "{m:?}");
        assert!(m.peak > 0.9999);
    }

    #[test]
    fn ncc_noise_template_weak() {
        let mut rng = Rng(3);
        let (iw, ih) = (100, 100);
        let img = Texture::new(&mut rng, 40, 1.0).image(iw, ih, 0.0, 0.0);
        let tpl = Template::new(32, 32, noise(&mut rng, 32 * 32), None);
        let r = match_template(&ImageView::new(iw, ih, &img), &tpl, 50.0, 50.0, 20, &NccParams::default());
        assert!(matches!(r, Err(NccReject::WeakPeak { peak }) if peak < 0.4), "{r:?}");
    }

    #[test]
    fn ncc_periodic_stripes_ambiguous() {
        let (iw, ih, w) = (100, 100, 32);
        for diagonal in [false, true] {
            let stripes = |x: f64, y: f64| {
                let s = if diagonal { x + 0.5 * y } else { x };
                (2.0 * std::f64::consts::PI * s / 9.0).sin()
                    + 0.3 * (2.0 * std::f64::consts::PI * y / 23.0).sin()
            };
            let img: Vec<f32> =
                (0..iw * ih).map(|k| stripes((k % iw) as f64, (k / iw) as f64) as f32).collect();
            let tpl = Template::new(w, w, cut(&img, iw, 30, 30, w, w), None);
            let r =
                match_template(&ImageView::new(iw, ih, &img), &tpl, 45.5, 45.5, 20, &NccParams::default());
            assert!(matches!(r, Err(NccReject::Ambiguous { peak, second }) if second > 0.9 * peak), "{r:?}");
        }
    }

    #[test]
    fn ncc_flat_template_rejected() {
        let img = vec![1f32; 80 * 80];
        let img = ImageView::new(80, 80, &img);
        let p = NccParams::default();
        let flat = Template::new(16, 16, vec![42.0; 256], None);
        assert_eq!(match_template(&img, &flat, 40.0, 40.0, 5, &p), Err(NccReject::TooFlat));
        // Varies only where masked out.
        let data: Vec<f32> = (0..256).map(|k| if k % 16 < 4 { k as f32 } else { 5.0 }).collect();
        let mask: Vec<bool> = (0..256).map(|k| k % 16 >= 4).collect();
        assert_eq!(
            match_template(&img, &Template::new(16, 16, data, Some(mask)), 40.0, 40.0, 5, &p),
            Err(NccReject::TooFlat)
        );
        let none = Template::new(4, 4, vec![1.0; 16], Some(vec![false; 16]));
        assert_eq!(match_template(&img, &none, 40.0, 40.0, 5, &p), Err(NccReject::TooFlat));
        // A flat image area gives NCC 0, not rounding noise, even next to texture.
        let mut rng = Rng(21);
        let (iw, ih) = (80, 40);
        let tex = Texture::new(&mut rng, 30, 1.0);
        for level in [1000.3f32, 997.1, 1003.7, 1012.9, 1020.4, 1.0] {
            let img: Vec<f32> = (0..iw * ih)
                .map(|k| {
                    let (x, y) = ((k % iw) as f64, (k / iw) as f64);
                    if x >= 40.0 {
                        level
                    } else {
                        1010.0 + 5.0 * tex.at(x, y) as f32
                    }
                })
                .collect();
            for mask in [None, Some(diamond_mask(&mut rng, 16, 16, 0.05))] {
                let tpl = Template::new(16, 16, noise(&mut rng, 256), mask);
                let s = ncc_surface(&ImageView::new(iw, ih, &img), &tpl, 0, 0, 60, 20);
                for (k, v) in s.iter().enumerate() {
                    assert!(k % 60 < 40 || *v == 0.0, "{level} {k}: {v}");
                }
            }
        }
    }

    #[test]
    fn ncc_out_of_image_and_border() {
        let mut rng = Rng(5);
        let (iw, ih, w) = (100, 90, 32);
        let img = Texture::new(&mut rng, 40, 1.0).image(iw, ih, 0.0, 0.0);
        let view = ImageView::new(iw, ih, &img);
        let p = NccParams::default();
        let tpl = Template::new(w, w, cut(&img, iw, 2, 3, w, w), None);
        for (u, v) in [(-30.0, 40.0), (40.0, 130.0), (200.0, 200.0), (f64::NAN, 3.0), (1e300, 0.0)] {
            assert_eq!(match_template(&view, &tpl, u, v, 10, &p), Err(NccReject::OutOfImage), "{u} {v}");
        }
        // Barely one or two placements fit.
        assert_eq!(match_template(&view, &tpl, 15.5 - 11.0, 40.0, 12, &p), Err(NccReject::OutOfImage));
        // Clipped search area: found next to the image border...
        let m = match_template(&view, &tpl, 2.0 + 15.5, 3.0 + 15.5, 10, &p).unwrap();
        assert!((m.u - 17.5).abs() < 0.03 && (m.v - 18.5).abs() < 0.03, "{m:?}");
        // ... but the same place at the edge of the search area is rejected.
        assert_eq!(
            match_template(&view, &tpl, 2.0 + 15.5 + 6.0, 3.0 + 15.5, 6, &p),
            Err(NccReject::PeakOnBorder)
        );
        // A masked template whose valid part fits although its box does not.
        let mask: Vec<bool> = (0..w * w).map(|k| k % w >= 8).collect();
        let tpl = Template::new(w, w, cut(&img, iw, 0, 40, w, w), Some(mask));
        let m = match_template(&view, &tpl, -4.0 + 15.5, 40.0 + 15.5, 6, &p).unwrap();
        assert!((m.u - 15.5).abs() < 0.03 && (m.v - 55.5).abs() < 0.03, "{m:?}");
    }

    /// Seconds a call of `f(k)` (k in 0..n) takes, the best of `batches`
    /// batches of `n` (the machine is shared), and the sum of what the calls
    /// returned (so that they are not optimised away).
    fn best_per_call(batches: usize, n: usize, mut f: impl FnMut(usize) -> f64) -> (f64, f64) {
        let (mut best, mut acc) = (f64::INFINITY, 0.0);
        for _ in 0..batches {
            let t = std::time::Instant::now();
            for k in 0..n {
                acc += f(k);
            }
            best = best.min(t.elapsed().as_secs_f64() / n as f64);
        }
        (best, acc)
    }

    /// cargo test -p trn-vision --release ncc -- --ignored --nocapture
    #[test]
    #[ignore]
    fn ncc_timing() {
        let mut rng = Rng(17);
        let (iw, ih, w) = (640, 480, 32);
        let img = Texture::new(&mut rng, 60, 0.8).image(iw, ih, 0.3, 0.7);
        let view = ImageView::new(iw, ih, &img);
        let p = NccParams { min_peak: -1.0, max_second_ratio: 10.0, ..Default::default() };
        let warped = Some(diamond_mask(&mut rng, w, w, 0.0));
        for (name, mask) in [("unmasked", None), ("warped mask", warped)] {
            let tpls: Vec<Template> = (0..64)
                .map(|k| Template::new(w, w, cut(&img, iw, 40 + 7 * k, 30 + 5 * k, w, w), mask.clone()))
                .collect();
            let (best, acc) = best_per_call(400, 10, |k| {
                let (x, y) = (40 + 7 * (k % 64), 30 + 5 * (k % 64));
                let (u0, v0) = (x as f64 + 15.5 + 3.0, y as f64 + 15.5 - 2.0);
                match_template(&view, &tpls[k % 64], u0, v0, 20, &p).map(|m| m.u).unwrap_or(0.0)
            });
            println!(
                "ncc {name} 32x32 template, radius 20 (41x41): {:.1} us per match ({acc:.0})",
                best * 1e6
            );
        }
        // An acquisition's search: a 23x23 template over the whole of a
        // 160x120 image (138x98 positions).
        let (iw, ih, w) = (160, 120, 23);
        let img = Texture::new(&mut rng, 20, 0.8).image(iw, ih, 0.3, 0.7);
        let view = ImageView::new(iw, ih, &img);
        let warped = Some(diamond_mask(&mut rng, w, w, 0.0));
        for (name, mask) in [("unmasked", None), ("warped mask", warped)] {
            let tpls: Vec<Template> = (0..16)
                .map(|k| Template::new(w, w, cut(&img, iw, 10 + 7 * k, 8 + 5 * k, w, w), mask.clone()))
                .collect();
            let (best, acc) = best_per_call(100, tpls.len(), |k| {
                let (u0, v0) = (10.0 + 7.0 * k as f64 + 11.0 + 9.0, 8.0 + 5.0 * k as f64 + 11.0 - 6.0);
                match_template(&view, &tpls[k], u0, v0, 160, &p).map(|m| m.u).unwrap_or(0.0)
            });
            let positions = ((iw - w + 1) * (ih - w + 1)) as f64;
            println!(
                "ncc {name} 23x23 template over a 160x120 image: {:.1} us per match, {:.1} ns a position ({acc:.0})",
                best * 1e6,
                best * 1e9 / positions
            );
        }
    }
}

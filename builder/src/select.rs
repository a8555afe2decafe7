//! Landmark selection on one window of a luminance raster: texture (Shi-Tomasi),
//! contrast, nodata and saturation tests, per-cell quotas, and a uniqueness test
//! (the template's NCC against its own neighbourhood). Pure: no I/O.

/// A luminance window with its validity mask, row-major.
pub struct LumWindow<'a> {
    pub width: usize,
    pub height: usize,
    pub lum: &'a [f32],
    pub valid: &'a [u8],
}

#[derive(Clone, Copy, Debug)]
pub struct SelectParams {
    /// Template window in window pixels (may be non-square for non-square source pixels).
    pub win_w: usize,
    pub win_h: usize,
    /// Cell size for the per-cell quota, in window pixels.
    pub cell_w: usize,
    pub cell_h: usize,
    pub per_cell: usize,
    /// Minimum Shi-Tomasi strength (grey levels^2 per pixel^2).
    pub min_shi_tomasi: f32,
    /// Minimum standard deviation of the template's grey levels.
    pub min_contrast_std: f32,
    /// Largest share of saturated (>= 250 or <= 5) pixels (clouds, snow, deep shadow).
    pub max_saturated: f32,
    /// Uniqueness search radius (window pixels) and the highest second peak accepted.
    pub search_radius: usize,
    pub max_second_peak: f32,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    /// Centre of the template window in window pixel coordinates (pixel centres at integers).
    pub x: usize,
    pub y: usize,
    pub shi_tomasi: f32,
    pub contrast_std: f32,
    pub second_peak_ncc: f32,
}

/// Box sums over a `win_w x win_h` window centred at each pixel (top-left at
/// `x - win_w/2`), on the grid of every `stride`-th pixel (output index
/// `gy * gw + gx` for pixel `(gx * stride, gy * stride)`, `gw = ceil(w / stride)`),
/// computed with running sums; entries whose window leaves the image are `NAN`.
pub fn box_sum(
    src: &[f32],
    width: usize,
    height: usize,
    win_w: usize,
    win_h: usize,
    stride: usize,
) -> Vec<f32> {
    let (gw, gh) = (width.div_ceil(stride), height.div_ceil(stride));
    let mut out = vec![f32::NAN; gw * gh];
    if win_w > width || win_h > height {
        return out;
    }
    let (hw, hh) = (win_w / 2, win_h / 2);
    // Horizontal running sums, evaluated only at grid columns: the window
    // advances `stride` pixels between outputs.
    let mut horiz = vec![f64::NAN; gw * height];
    let first = hw.next_multiple_of(stride);
    for y in 0..height {
        let row = &src[y * width..(y + 1) * width];
        let out_row = &mut horiz[y * gw..(y + 1) * gw];
        let mut x = first;
        if x + win_w - hw > width {
            continue;
        }
        // f64 accumulator: no drift across long rows.
        let mut acc: f64 = row[x - hw..x - hw + win_w].iter().map(|&v| v as f64).sum();
        out_row[x / stride] = acc;
        while x + stride + win_w - hw <= width {
            let (old, new) = (x - hw, x - hw + win_w);
            for k in 0..stride {
                acc += row[new + k] as f64 - row[old + k] as f64;
            }
            x += stride;
            out_row[x / stride] = acc;
        }
    }
    let mut acc = vec![0f64; gw];
    for y in 0..win_h {
        for (a, h) in acc.iter_mut().zip(&horiz[y * gw..(y + 1) * gw]) {
            *a += h;
        }
    }
    let emit = |y: usize, acc: &[f64], out: &mut [f32]| {
        if y % stride == 0 {
            for (o, a) in out[(y / stride) * gw..(y / stride + 1) * gw].iter_mut().zip(acc) {
                *o = *a as f32;
            }
        }
    };
    emit(hh, &acc, &mut out);
    for y0 in 1..=(height - win_h) {
        let (add, sub) = ((y0 + win_h - 1) * gw, (y0 - 1) * gw);
        for x in 0..gw {
            acc[x] += horiz[add + x] - horiz[sub + x];
        }
        emit(y0 + hh, &acc, &mut out);
    }
    out
}

/// Per-pixel selection measures of a window, on the grid of every `stride`-th pixel.
pub struct Measures {
    pub stride: usize,
    pub grid_w: usize,
    pub shi_tomasi: Vec<f32>,
    pub contrast_std: Vec<f32>,
    /// Window fully valid and not too saturated.
    pub usable: Vec<bool>,
}

impl Measures {
    fn index(&self, x: usize, y: usize) -> usize {
        (y / self.stride) * self.grid_w + x / self.stride
    }
}

/// Candidate centres are taken on a 2-pixel grid: a quarter of the work, and a
/// landmark's exact centre does not matter.
pub const GRID_STRIDE: usize = 2;

pub fn measures(img: &LumWindow, p: &SelectParams) -> Measures {
    let (w, h) = (img.width, img.height);
    let n = w * h;
    let mut gxx = vec![0f32; n];
    let mut gyy = vec![0f32; n];
    let mut gxy = vec![0f32; n];
    // Invalid pixels weigh INVALID, saturated ones 1: one box sum tells both.
    const INVALID: f32 = 4096.0;
    let mut bad = vec![0f32; n];
    let mut lum2 = vec![0f32; n];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let v = img.lum[i];
            bad[i] = if img.valid[i] == 0 {
                INVALID
            } else if !(5.0..250.0).contains(&v) {
                1.0
            } else {
                0.0
            };
            lum2[i] = v * v;
            if x > 0 && x + 1 < w && y > 0 && y + 1 < h {
                let gx = 0.5 * (img.lum[i + 1] - img.lum[i - 1]);
                let gy = 0.5 * (img.lum[i + w] - img.lum[i - w]);
                gxx[i] = gx * gx;
                gyy[i] = gy * gy;
                gxy[i] = gx * gy;
            }
        }
    }
    let (ww, wh, st) = (p.win_w, p.win_h, GRID_STRIDE);
    let area = (ww * wh) as f32;
    let sxx = box_sum(&gxx, w, h, ww, wh, st);
    let syy = box_sum(&gyy, w, h, ww, wh, st);
    let sxy = box_sum(&gxy, w, h, ww, wh, st);
    let s1 = box_sum(img.lum, w, h, ww, wh, st);
    let s2 = box_sum(&lum2, w, h, ww, wh, st);
    // One pixel more on each side: bilinear resampling reaches past the window.
    let sbad = box_sum(&bad, w, h, ww + 2, wh + 2, st);
    let g = sxx.len();
    let mut shi_tomasi = vec![0f32; g];
    let mut contrast_std = vec![0f32; g];
    let mut usable = vec![false; g];
    for i in 0..g {
        if sxx[i].is_nan() || sbad[i].is_nan() {
            continue;
        }
        let (a, c, b) = (sxx[i] / area, syy[i] / area, sxy[i] / area);
        // Smaller eigenvalue of [[a, b], [b, c]] (Shi & Tomasi 1994).
        let lmin = 0.5 * (a + c) - (0.25 * (a - c) * (a - c) + b * b).sqrt();
        let mean = s1[i] / area;
        let var = (s2[i] / area - mean * mean).max(0.0);
        shi_tomasi[i] = lmin;
        contrast_std[i] = var.sqrt();
        usable[i] = sbad[i] < INVALID - 0.5 && sbad[i] / ((ww + 2) * (wh + 2)) as f32 <= p.max_saturated;
    }
    Measures { stride: st, grid_w: w.div_ceil(st), shi_tomasi, contrast_std, usable }
}

/// A template cut from a window, zero-mean, sampled every `step`-th pixel.
pub struct Patch {
    cx: usize,
    cy: usize,
    win_w: usize,
    win_h: usize,
    step: usize,
    values: Vec<f32>,
    norm: f32,
}

impl Patch {
    pub fn new(
        img: &LumWindow,
        cx: usize,
        cy: usize,
        win_w: usize,
        win_h: usize,
        step: usize,
    ) -> Option<Self> {
        let (x0, y0) = (cx.checked_sub(win_w / 2)?, cy.checked_sub(win_h / 2)?);
        if x0 + win_w > img.width || y0 + win_h > img.height {
            return None;
        }
        let mut values = Vec::new();
        for r in (0..win_h).step_by(step) {
            let row = &img.lum[(y0 + r) * img.width + x0..][..win_w];
            values.extend(row.iter().step_by(step));
        }
        let mean = values.iter().map(|&v| v as f64).sum::<f64>() / values.len() as f64;
        values.iter_mut().for_each(|v| *v -= mean as f32);
        let norm = values.iter().map(|&v| (v as f64) * v as f64).sum::<f64>() as f32;
        Some(Self { cx, cy, win_w, win_h, step, values, norm })
    }

    /// NCC with the window shifted by (dx, dy); `None` when it leaves the image
    /// or either side is flat.
    pub fn ncc(&self, img: &LumWindow, dx: isize, dy: isize) -> Option<f32> {
        let sx0 = self.cx as isize - (self.win_w / 2) as isize + dx;
        let sy0 = self.cy as isize - (self.win_h / 2) as isize + dy;
        if sx0 < 0
            || sy0 < 0
            || sx0 as usize + self.win_w > img.width
            || sy0 as usize + self.win_h > img.height
        {
            return None;
        }
        let (sx0, sy0) = (sx0 as usize, sy0 as usize);
        let cols = self.win_w.div_ceil(self.step);
        let (mut ts, mut ss, mut s1) = (0f32, 0f32, 0f32);
        for (k, r) in (0..self.win_h).step_by(self.step).enumerate() {
            let srow = &img.lum[(sy0 + r) * img.width + sx0..][..self.win_w];
            let trow = &self.values[k * cols..(k + 1) * cols];
            if self.step == 1 {
                for (&t, &s) in trow.iter().zip(srow) {
                    ts += t * s;
                    ss += s * s;
                    s1 += s;
                }
            } else {
                for (&t, &s) in trow.iter().zip(srow.iter().step_by(self.step)) {
                    ts += t * s;
                    ss += s * s;
                    s1 += s;
                }
            }
        }
        // Sum of t' * s equals sum of t' * (s - mean s) because t' has zero mean.
        let n = self.values.len() as f32;
        let vs = ss - s1 * s1 / n;
        if vs <= 1e-6 || self.norm <= 1e-6 {
            return None;
        }
        Some(ts / (self.norm * vs).sqrt())
    }
}

/// Normalised cross-correlation of the template centred at (cx, cy) with the
/// window shifted by (dx, dy), sampling every `step`-th pixel.
#[allow(clippy::too_many_arguments)]
pub fn ncc_shift(
    img: &LumWindow,
    cx: usize,
    cy: usize,
    dx: isize,
    dy: isize,
    win_w: usize,
    win_h: usize,
    step: usize,
) -> Option<f32> {
    Patch::new(img, cx, cy, win_w, win_h, step)?.ncc(img, dx, dy)
}

/// Highest NCC of the template at (cx, cy) against shifts within `radius`,
/// outside the main correlation lobe. The lobe is the connected region of shifts
/// around (0, 0) where the NCC decreases monotonically outwards, approximated by
/// the shifts with |d| <= `exclude` (2 px covers the lobe of textured,
/// band-limited imagery). Shifts are evaluated on a grid of `step`.
pub fn second_peak(
    img: &LumWindow,
    cx: usize,
    cy: usize,
    p: &SelectParams,
    exclude: isize,
    step: usize,
) -> f32 {
    let Some(patch) = Patch::new(img, cx, cy, p.win_w, p.win_h, step) else {
        return 1.0;
    };
    let r = p.search_radius as isize;
    let mut best = -1f32;
    let mut dy = -r;
    while dy <= r {
        let mut dx = -r;
        while dx <= r {
            if dx.abs().max(dy.abs()) > exclude {
                if let Some(v) = patch.ncc(img, dx, dy) {
                    best = best.max(v);
                }
            }
            dx += step as isize;
        }
        dy += step as isize;
    }
    best
}

/// The part of a window whose pixels a tile owns (half-open, window pixels).
/// Its corner must sit on the global cell grid so that adjacent tiles never
/// pick the same landmark.
#[derive(Clone, Copy, Debug)]
pub struct Core {
    pub x0: usize,
    pub x1: usize,
    pub y0: usize,
    pub y1: usize,
}

/// Selects up to `per_cell` landmarks in each cell of the core.
pub fn select(img: &LumWindow, p: &SelectParams, core: Core) -> Vec<Candidate> {
    let m = measures(img, p);
    let mut out = Vec::new();
    let mut cy0 = core.y0;
    while cy0 < core.y1 {
        let cy1 = (cy0 + p.cell_h).min(core.y1);
        let mut cx0 = core.x0;
        while cx0 < core.x1 {
            let cx1 = (cx0 + p.cell_w).min(core.x1);
            // Best few positions in the cell, strongest texture first.
            let mut cell: Vec<(f32, usize, usize)> = Vec::new();
            for y in (cy0.next_multiple_of(m.stride)..cy1).step_by(m.stride) {
                for x in (cx0.next_multiple_of(m.stride)..cx1).step_by(m.stride) {
                    let i = m.index(x, y);
                    if m.usable[i]
                        && m.shi_tomasi[i] >= p.min_shi_tomasi
                        && m.contrast_std[i] >= p.min_contrast_std
                    {
                        cell.push((m.shi_tomasi[i], x, y));
                    }
                }
            }
            // Only the strongest few are ever tried: a partial sort is enough.
            let keep = 32 * p.per_cell;
            if cell.len() > keep {
                cell.select_nth_unstable_by(keep, |a, b| b.0.total_cmp(&a.0));
                cell.truncate(keep);
            }
            cell.sort_unstable_by(|a, b| b.0.total_cmp(&a.0));
            let mut taken: Vec<(usize, usize)> = Vec::new();
            let min_sep = (p.win_w.min(p.win_h) / 2).max(1);
            let mut tried = 0;
            for &(st, x, y) in &cell {
                if taken.len() >= p.per_cell || tried >= 3 * p.per_cell {
                    break;
                }
                if taken.iter().any(|&(tx, ty)| tx.abs_diff(x).max(ty.abs_diff(y)) < min_sep) {
                    continue;
                }
                tried += 1;
                // Coarse pass on a 2-pixel grid, exact pass only when it is close.
                let coarse = second_peak(img, x, y, p, 2, 2);
                if coarse > p.max_second_peak {
                    continue;
                }
                let sp =
                    if coarse > p.max_second_peak - 0.15 { second_peak(img, x, y, p, 2, 1) } else { coarse };
                if sp > p.max_second_peak {
                    continue;
                }
                taken.push((x, y));
                out.push(Candidate {
                    x,
                    y,
                    shi_tomasi: st,
                    contrast_std: m.contrast_std[m.index(x, y)],
                    second_peak_ncc: sp,
                });
            }
            cx0 = cx1;
        }
        cy0 = cy1;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn noise(w: usize, h: usize, seed: u64) -> Vec<f32> {
        let mut s = seed;
        (0..w * h)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((s >> 33) % 200) as f32 + 20.0
            })
            .collect()
    }

    #[test]
    fn box_sum_matches_brute_force() {
        let (w, h) = (37, 29);
        let src = noise(w, h, 3);
        for &(ww, wh, st) in &[(5, 5, 1), (6, 4, 1), (1, 1, 1), (37, 29, 1), (5, 5, 2), (6, 3, 2), (4, 4, 3)]
        {
            let got = box_sum(&src, w, h, ww, wh, st);
            let gw = w.div_ceil(st);
            assert_eq!(got.len(), gw * h.div_ceil(st));
            for y in (0..h).step_by(st) {
                for x in (0..w).step_by(st) {
                    let (x0, y0) = (x as isize - (ww / 2) as isize, y as isize - (wh / 2) as isize);
                    let inside = x0 >= 0 && y0 >= 0 && x0 as usize + ww <= w && y0 as usize + wh <= h;
                    let g = got[(y / st) * gw + x / st];
                    if !inside {
                        assert!(g.is_nan());
                        continue;
                    }
                    let mut s = 0f64;
                    for yy in 0..wh {
                        for xx in 0..ww {
                            s += src[(y0 as usize + yy) * w + x0 as usize + xx] as f64;
                        }
                    }
                    assert!((g as f64 - s).abs() < 1e-2 * s.abs().max(1.0) * 1e-3, "{g} vs {s}");
                }
            }
        }
    }

    #[test]
    fn ncc_shift_matches_definition_and_self_is_one() {
        let (w, h) = (40, 40);
        let lum = noise(w, h, 9);
        let valid = vec![1u8; w * h];
        let img = LumWindow { width: w, height: h, lum: &lum, valid: &valid };
        assert!((ncc_shift(&img, 20, 20, 0, 0, 9, 9, 1).unwrap() - 1.0).abs() < 1e-6);
        // Brute-force NCC by definition.
        let (dx, dy) = (3isize, -2isize);
        let t: Vec<f64> = (0..81).map(|k| lum[(16 + k / 9) * w + 16 + k % 9] as f64).collect();
        let s: Vec<f64> = (0..81)
            .map(|k| lum[((16 + dy) as usize + k / 9) * w + (16 + dx) as usize + k % 9] as f64)
            .collect();
        let (mt, ms) = (t.iter().sum::<f64>() / 81.0, s.iter().sum::<f64>() / 81.0);
        let num: f64 = t.iter().zip(&s).map(|(a, b)| (a - mt) * (b - ms)).sum();
        let den = (t.iter().map(|a| (a - mt).powi(2)).sum::<f64>()
            * s.iter().map(|b| (b - ms).powi(2)).sum::<f64>())
        .sqrt();
        let got = ncc_shift(&img, 20, 20, dx, dy, 9, 9, 1).unwrap() as f64;
        assert!((got - num / den).abs() < 1e-5);
        assert!(ncc_shift(&img, 20, 20, 30, 0, 9, 9, 1).is_none());
    }

    fn params() -> SelectParams {
        SelectParams {
            win_w: 15,
            win_h: 15,
            cell_w: 30,
            cell_h: 30,
            per_cell: 1,
            min_shi_tomasi: 1.0,
            min_contrast_std: 4.0,
            max_saturated: 0.1,
            search_radius: 6,
            max_second_peak: 0.9,
        }
    }

    #[test]
    fn flat_and_nodata_areas_are_rejected_texture_is_taken() {
        let (w, h) = (120, 60);
        let mut lum = noise(w, h, 5);
        let mut valid = vec![1u8; w * h];
        for y in 0..h {
            for x in 0..w {
                if x < 40 {
                    lum[y * w + x] = 100.0; // water: flat
                } else if x >= 80 {
                    valid[y * w + x] = 0; // nodata
                }
            }
        }
        let img = LumWindow { width: w, height: h, lum: &lum, valid: &valid };
        let c = select(&img, &params(), Core { x0: 0, x1: w, y0: 0, y1: h });
        assert!(!c.is_empty());
        for k in &c {
            assert!(k.x - 7 >= 40 && k.x + 7 < 80, "candidate in flat or nodata area: {k:?}");
        }
    }

    #[test]
    fn periodic_texture_is_not_unique() {
        // A pattern repeating every 4 pixels correlates perfectly at a 4-pixel shift.
        let (w, h) = (60, 60);
        let base = noise(4, 4, 1);
        let lum: Vec<f32> = (0..w * h).map(|i| base[(i / w % 4) * 4 + i % w % 4]).collect();
        let valid = vec![1u8; w * h];
        let img = LumWindow { width: w, height: h, lum: &lum, valid: &valid };
        assert!(select(&img, &params(), Core { x0: 0, x1: w, y0: 0, y1: h }).is_empty());
        let sp = second_peak(&img, 30, 30, &params(), 2, 1);
        assert!(sp > 0.999);
    }
}

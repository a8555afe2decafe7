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
/// `x - win_w/2`), computed with running sums; entries whose window leaves the
/// image are `f32::NAN`.
pub fn box_sum(src: &[f32], width: usize, height: usize, win_w: usize, win_h: usize) -> Vec<f32> {
    let mut horiz = vec![f32::NAN; width * height];
    let (hw, hh) = (win_w / 2, win_h / 2);
    if win_w > width || win_h > height {
        return horiz;
    }
    for y in 0..height {
        let row = &src[y * width..(y + 1) * width];
        let out = &mut horiz[y * width..(y + 1) * width];
        // f64 accumulator: no drift across long rows.
        let mut acc: f64 = row[..win_w].iter().map(|&v| v as f64).sum();
        out[hw] = acc as f32;
        for x0 in 1..=(width - win_w) {
            acc += row[x0 + win_w - 1] as f64 - row[x0 - 1] as f64;
            out[x0 + hw] = acc as f32;
        }
    }
    let mut out = vec![f32::NAN; width * height];
    let mut acc = vec![0f64; width];
    for y in 0..win_h {
        for x in 0..width {
            acc[x] += horiz[y * width + x] as f64;
        }
    }
    for x in 0..width {
        out[hh * width + x] = acc[x] as f32;
    }
    for y0 in 1..=(height - win_h) {
        let (add, sub) = ((y0 + win_h - 1) * width, (y0 - 1) * width);
        for x in 0..width {
            acc[x] += horiz[add + x] as f64 - horiz[sub + x] as f64;
            out[(y0 + hh) * width + x] = acc[x] as f32;
        }
    }
    out
}

/// Per-pixel selection measures of a window.
pub struct Measures {
    pub shi_tomasi: Vec<f32>,
    pub contrast_std: Vec<f32>,
    /// Window fully valid and not too saturated.
    pub usable: Vec<bool>,
}

pub fn measures(img: &LumWindow, p: &SelectParams) -> Measures {
    let (w, h) = (img.width, img.height);
    let n = w * h;
    let mut gxx = vec![0f32; n];
    let mut gyy = vec![0f32; n];
    let mut gxy = vec![0f32; n];
    let mut invalid = vec![0f32; n];
    let mut saturated = vec![0f32; n];
    let mut lum2 = vec![0f32; n];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let v = img.lum[i];
            invalid[i] = if img.valid[i] == 0 { 1.0 } else { 0.0 };
            saturated[i] = if !(5.0..250.0).contains(&v) { 1.0 } else { 0.0 };
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
    let (ww, wh) = (p.win_w, p.win_h);
    let area = (ww * wh) as f32;
    let sxx = box_sum(&gxx, w, h, ww, wh);
    let syy = box_sum(&gyy, w, h, ww, wh);
    let sxy = box_sum(&gxy, w, h, ww, wh);
    let s1 = box_sum(img.lum, w, h, ww, wh);
    let s2 = box_sum(&lum2, w, h, ww, wh);
    // One pixel more on each side: bilinear resampling reaches past the window.
    let sinv = box_sum(&invalid, w, h, ww + 2, wh + 2);
    let ssat = box_sum(&saturated, w, h, ww, wh);
    let mut shi_tomasi = vec![0f32; n];
    let mut contrast_std = vec![0f32; n];
    let mut usable = vec![false; n];
    for i in 0..n {
        if sxx[i].is_nan() {
            continue;
        }
        let (a, c, b) = (sxx[i] / area, syy[i] / area, sxy[i] / area);
        // Smaller eigenvalue of [[a, b], [b, c]] (Shi & Tomasi 1994).
        let lmin = 0.5 * (a + c) - (0.25 * (a - c) * (a - c) + b * b).sqrt();
        let mean = s1[i] / area;
        let var = (s2[i] / area - mean * mean).max(0.0);
        shi_tomasi[i] = lmin;
        contrast_std[i] = var.sqrt();
        usable[i] = sinv[i] < 0.5 && ssat[i] / area <= p.max_saturated;
    }
    Measures { shi_tomasi, contrast_std, usable }
}

/// Normalised cross-correlation of the template centred at (cx, cy) with the
/// window shifted by (dx, dy), sampling every `step`-th pixel. `None` when the
/// shifted window leaves the image or either patch is flat.
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
    let (x0, y0) = (cx as isize - (win_w / 2) as isize, cy as isize - (win_h / 2) as isize);
    let (sx0, sy0) = (x0 + dx, y0 + dy);
    if x0 < 0 || y0 < 0 || sx0 < 0 || sy0 < 0 {
        return None;
    }
    let (w, h) = (img.width as isize, img.height as isize);
    if x0 + win_w as isize > w
        || y0 + win_h as isize > h
        || sx0 + win_w as isize > w
        || sy0 + win_h as isize > h
    {
        return None;
    }
    let (mut st, mut ss, mut stt, mut sss, mut sts, mut n) = (0f64, 0f64, 0f64, 0f64, 0f64, 0f64);
    for r in (0..win_h).step_by(step) {
        let trow = &img.lum[(y0 as usize + r) * img.width + x0 as usize..][..win_w];
        let srow = &img.lum[(sy0 as usize + r) * img.width + sx0 as usize..][..win_w];
        for c in (0..win_w).step_by(step) {
            let (t, s) = (trow[c] as f64, srow[c] as f64);
            st += t;
            ss += s;
            stt += t * t;
            sss += s * s;
            sts += t * s;
            n += 1.0;
        }
    }
    let vt = stt - st * st / n;
    let vs = sss - ss * ss / n;
    if vt <= 1e-9 || vs <= 1e-9 {
        return None;
    }
    Some(((sts - st * ss / n) / (vt * vs).sqrt()) as f32)
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
    let r = p.search_radius as isize;
    let mut best = -1f32;
    let mut dy = -r;
    while dy <= r {
        let mut dx = -r;
        while dx <= r {
            if dx.abs().max(dy.abs()) > exclude {
                if let Some(v) = ncc_shift(img, cx, cy, dx, dy, p.win_w, p.win_h, step) {
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
    let w = img.width;
    let mut cy0 = core.y0;
    while cy0 < core.y1 {
        let cy1 = (cy0 + p.cell_h).min(core.y1);
        let mut cx0 = core.x0;
        while cx0 < core.x1 {
            let cx1 = (cx0 + p.cell_w).min(core.x1);
            // Best few positions in the cell, strongest texture first.
            let mut cell: Vec<(f32, usize, usize)> = Vec::new();
            for y in cy0..cy1 {
                for x in cx0..cx1 {
                    let i = y * w + x;
                    if m.usable[i]
                        && m.shi_tomasi[i] >= p.min_shi_tomasi
                        && m.contrast_std[i] >= p.min_contrast_std
                    {
                        cell.push((m.shi_tomasi[i], x, y));
                    }
                }
            }
            cell.sort_by(|a, b| b.0.total_cmp(&a.0));
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
                    contrast_std: m.contrast_std[y * w + x],
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
        for &(ww, wh) in &[(5, 5), (6, 4), (1, 1), (37, 29)] {
            let got = box_sum(&src, w, h, ww, wh);
            for y in 0..h {
                for x in 0..w {
                    let (x0, y0) = (x as isize - (ww / 2) as isize, y as isize - (wh / 2) as isize);
                    let inside = x0 >= 0 && y0 >= 0 && x0 as usize + ww <= w && y0 as usize + wh <= h;
                    let g = got[y * w + x];
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

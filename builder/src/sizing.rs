//! Which template levels a database holds: a ladder of template *footprints*
//! (ground side of a template) doubling from level to level, each cut at the
//! ortho's own resolution with few pixels (fine levels) or from coarser
//! pyramid levels with more (coarse levels), sized so that every camera
//! resolution the database serves sees some level's templates span
//! [`MIN_SPAN_PX`]..[`MAX_SPAN_PX`] image pixels. Pure: no I/O.
//!
//! A navigator picks, for a ground resolution of `g` metres per image pixel,
//! the level whose footprint spans closest to [`TARGET_SPAN_PX`] pixels (the
//! navigator's own constant of the same value); with footprints doubling,
//! that level spans `TARGET/√2 .. TARGET·√2` pixels.

use serde::Serialize;

/// Image pixels a navigator wants a template to span (the navigator's
/// `view::TARGET_PATCH_PX`).
pub const TARGET_SPAN_PX: f64 = 32.0;
/// Fewest and most image pixels a template of a used level may span.
pub const MIN_SPAN_PX: f64 = 12.0;
pub const MAX_SPAN_PX: f64 = 48.0;

/// The cameras a database built without `--camera` serves: 160x120 to
/// 1024x768 pixels, 20-60 degree horizontal fields of view, 2 to 40 km
/// above the terrain, looking down.
pub const DEFAULT_ENVELOPE: Envelope = Envelope {
    finest_camera: CameraSpan { width_px: 1024, hfov_deg: 20.0, altitude_m: 2_000.0 },
    coarsest_camera: CameraSpan { width_px: 160, hfov_deg: 60.0, altitude_m: 40_000.0 },
};

#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct CameraSpan {
    pub width_px: u32,
    pub hfov_deg: f64,
    pub altitude_m: f64,
}

impl CameraSpan {
    /// Ground sample distance straight down (m per pixel).
    pub fn nadir_gsd_m(&self) -> f64 {
        let f = self.width_px as f64 / 2.0 / (self.hfov_deg.to_radians() / 2.0).tan();
        self.altitude_m / f
    }
}

/// The finest- and coarsest-resolution cameras of a default database; it
/// serves every camera between them: widths from the coarsest's to the
/// finest's (4:3 images), fields of view and heights in the same way.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Envelope {
    pub finest_camera: CameraSpan,
    pub coarsest_camera: CameraSpan,
}

impl Envelope {
    /// The narrowest ground (m across) that any camera of the envelope with a
    /// ground resolution of `gsd_m` m per pixel sees straight down: the
    /// narrowest field at the lowest height, or the fewest pixels.
    pub fn min_ground_width_m(&self, gsd_m: f64) -> f64 {
        let f = &self.finest_camera;
        let narrowest = 2.0 * f.altitude_m * (f.hfov_deg.to_radians() / 2.0).tan();
        narrowest.max(self.coarsest_camera.width_px as f64 * gsd_m)
    }

    /// Cell side (share of a template footprint) for a level of footprint
    /// `footprint_m`: one footprint, or more (at most 2) while every camera of
    /// the envelope that picks the level still sees [`CELLS_IN_VIEW`] cells
    /// where its templates span their widest (`TARGET·√2` px; fewer ground
    /// metres in view than anywhere else the level is picked).
    pub fn spacing_share(&self, footprint_m: f64) -> f64 {
        let gsd = footprint_m / (TARGET_SPAN_PX * std::f64::consts::SQRT_2);
        let across = self.min_ground_width_m(gsd) / footprint_m;
        let cells_at_one = across * across * 0.75;
        (cells_at_one / CELLS_IN_VIEW).sqrt().clamp(1.0, 2.0)
    }
}

/// A mission: one camera, flown between two heights above the terrain,
/// looking at most `max_off_nadir_deg` away from straight down (boresight).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Mission {
    pub width_px: u32,
    pub height_px: u32,
    /// Focal lengths (pixels).
    pub fx: f64,
    pub fy: f64,
    pub altitude_min_m: f64,
    pub altitude_max_m: f64,
    pub max_off_nadir_deg: f64,
}

/// Selection cells a mission's camera should see (about half hold a usable
/// landmark over real scenes with water and bare ground: 60 in view).
pub const CELLS_IN_VIEW: f64 = 120.0;

/// The share of cells a mission database's density fill aims to give a
/// landmark: where fewer hold one (water, bare ground), the textured cells keep
/// more. Above the half that 60 of [`CELLS_IN_VIEW`] need, since a view cuts
/// the cells at its edges (on the salt lake mission, 0.5 left 49 in the
/// sparsest view, 0.7 left 82).
pub const USABLE_SHARE: f64 = 0.7;

/// [`CELLS_IN_VIEW`] cells as a 4:3 window (columns, rows): 13 x 9 = 117.
pub const VIEW_CELLS: (usize, usize) = (13, 9);

/// Largest view angle from the vertical at which the navigator uses a
/// landmark (its default incidence limit).
pub const MAX_VIEW_DEG: f64 = 75.0;

impl Mission {
    /// Largest angle between a ray in view and the vertical: the boresight's
    /// tilt plus half the diagonal field of view, at most [`MAX_VIEW_DEG`].
    pub fn max_view_deg(&self) -> f64 {
        let (hw, hh) = (self.width_px as f64 / 2.0 / self.fx, self.height_px as f64 / 2.0 / self.fy);
        let half_diag = hw.hypot(hh).atan().to_degrees();
        (self.max_off_nadir_deg + half_diag).min(MAX_VIEW_DEG)
    }

    /// Cell side (share of a template footprint) that puts at least
    /// [`CELLS_IN_VIEW`] selection cells in the image where a level's
    /// templates span `span_px` pixels: half a footprint to one. Never
    /// coarser than the default database's one footprint: a large image
    /// would get by with fewer, but the landmarks beyond the 60 it needs
    /// buy accuracy (on the realistic oblique balloon, cells of 1.8
    /// footprints navigated to 61 m, the default's one footprint to 32 m:
    /// more relief in view for the self-calibration, more map errors to
    /// average).
    pub fn spacing_share(&self, span_px: f64) -> f64 {
        let footprints = (self.width_px as f64 / span_px) * (self.height_px as f64 / span_px);
        (footprints / CELLS_IN_VIEW).sqrt().clamp(0.5, 1.0)
    }

    /// The camera's ground resolutions over the mission: from straight down
    /// at the lowest height to the most oblique ray at the highest, stretched
    /// by the incidence as navigators count it (range / f / sqrt(cos)).
    pub fn gsd_range(&self) -> GsdRange {
        let cos = self.max_view_deg().to_radians().cos();
        GsdRange {
            finest_m: self.altitude_min_m / self.fx.max(self.fy),
            coarsest_m: self.altitude_max_m / self.fx.min(self.fy) / (cos * cos.sqrt()),
        }
    }
}

/// Camera ground sample distances (m per image pixel) a database serves.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct GsdRange {
    pub finest_m: f64,
    pub coarsest_m: f64,
}

impl GsdRange {
    pub fn of_envelope(e: &Envelope) -> Self {
        GsdRange { finest_m: e.finest_camera.nadir_gsd_m(), coarsest_m: e.coarsest_camera.nadir_gsd_m() }
    }
}

/// One template level.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct LevelSpec {
    pub level: u8,
    /// Template pixel size on the ground (m): `base_gsd * 2^gsd_step`.
    pub gsd_m: f64,
    pub gsd_step: u32,
    /// Template side (pixels).
    pub size_px: u32,
}

impl LevelSpec {
    /// Ground side of a template (m).
    pub fn footprint_m(&self) -> f64 {
        self.gsd_m * self.size_px as f64
    }

    /// Camera resolutions (m per pixel) at which this level's templates span
    /// [`MIN_SPAN_PX`]..[`MAX_SPAN_PX`] pixels.
    pub fn serves(&self) -> GsdRange {
        GsdRange { finest_m: self.footprint_m() / MAX_SPAN_PX, coarsest_m: self.footprint_m() / MIN_SPAN_PX }
    }
}

/// The level ladder: footprints `s0 * base * 2^(j0 + k)`, where `s0` is half
/// `max_size` when that is at least `min_size` (small native-resolution
/// templates for cameras finer than the ortho), else `max_size`; each level
/// cut at the finest pyramid GSD `base * 2^q` that keeps it within
/// `max_size` pixels. The finest level is the coarsest one whose footprint
/// still spans at most [`MAX_SPAN_PX`] pixels at `range.finest_m` (or the
/// smallest footprint the ortho allows: `s0` native pixels); levels are
/// added until one spans at least `TARGET/√2` pixels at `range.coarsest_m`,
/// or to `levels` when given. At most 12 levels.
pub fn ladder(
    base_gsd_m: f64,
    min_size: u32,
    max_size: u32,
    range: &GsdRange,
    levels: Option<u8>,
) -> Vec<LevelSpec> {
    let s0 = if max_size / 2 >= min_size { max_size / 2 } else { max_size };
    let f_unit = s0 as f64 * base_gsd_m;
    let sqrt2 = std::f64::consts::SQRT_2;
    let j0 = ((MAX_SPAN_PX * range.finest_m / f_unit).log2() + 1e-9).floor().max(0.0) as u32;
    let count = levels.map(u32::from).unwrap_or_else(|| {
        let mut n = 1;
        while n < 12 && f_unit * 2f64.powi((j0 + n - 1) as i32) < TARGET_SPAN_PX / sqrt2 * range.coarsest_m {
            n += 1;
        }
        n
    });
    (0..count.min(12))
        .map(|k| {
            let m = j0 + k;
            // Footprint = s0 * 2^m native pixels; the pyramid step q keeps the
            // side s0 * 2^(m - q) within max_size.
            let q = (0..=m).find(|&q| (s0 as u64) << (m - q) <= max_size as u64).unwrap_or(m);
            LevelSpec {
                level: k as u8,
                gsd_m: base_gsd_m * 2f64.powi(q as i32),
                gsd_step: q,
                size_px: s0 << (m - q),
            }
        })
        .collect()
}

/// Cell side of each level (share of its footprint). A level is used down to
/// the resolution where the next finer one takes over, where its templates
/// span their widest: `TARGET·√2` px, or more for the finest level when the
/// camera resolves finer than the ortho can serve (its templates then span
/// `footprint / range.finest_m` px, and fewer fit in the image). With a
/// mission: what puts [`CELLS_IN_VIEW`] cells in its camera's view there
/// ([`Mission::spacing_share`]). Without one: half a footprint for a finest
/// level that spans more than [`MAX_SPAN_PX`] at the finest resolution asked
/// for (an ortho too coarse to serve it), else what the default envelope
/// needs ([`Envelope::spacing_share`]: one footprint, more for small
/// footprints that only large images see).
pub fn spacing_shares(levels: &[LevelSpec], range: &GsdRange, mission: Option<&Mission>) -> Vec<f64> {
    levels
        .iter()
        .zip(widest_spans(levels, range))
        .map(|(l, span)| match mission {
            Some(m) => m.spacing_share(span),
            None if too_coarse(span) => 0.5,
            None => DEFAULT_ENVELOPE.spacing_share(l.footprint_m()),
        })
        .collect()
}

/// Whether a level whose templates span `span_px` at their widest is finer
/// than its ortho can serve: the default envelope's finest level on an ortho
/// coarser than its finest cameras (see [`spacing_shares`]).
fn too_coarse(span_px: f64) -> bool {
    span_px > MAX_SPAN_PX * 1.001
}

/// Where each level's templates span their widest in an image (px): see
/// [`spacing_shares`].
fn widest_spans(levels: &[LevelSpec], range: &GsdRange) -> Vec<f64> {
    let widest = TARGET_SPAN_PX * std::f64::consts::SQRT_2;
    let finest = |k: usize, l: &LevelSpec| {
        if k == 0 {
            (l.footprint_m() / range.finest_m).max(widest)
        } else {
            widest
        }
    };
    levels.iter().enumerate().map(|(k, l)| finest(k, l)).collect()
}

/// One level's density fill: its window, in selection cells, and the share
/// of the window's cells it aims to give a landmark (0: no fill).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FillWindow {
    pub cols: usize,
    pub rows: usize,
    pub share: f64,
}

impl FillWindow {
    /// The [`VIEW_CELLS`] window aiming at `share`.
    fn view(share: f64) -> Self {
        FillWindow { cols: VIEW_CELLS.0, rows: VIEW_CELLS.1, share }
    }
}

/// The density fill's window and share per level: [`VIEW_CELLS`] and `share`
/// where a camera sees about [`CELLS_IN_VIEW`] cells; where a mission's
/// camera sees more (a large image, whose cells are capped at one
/// footprint), the window is its view and the share what gives as many
/// landmarks as `share` of [`CELLS_IN_VIEW`] would, so a view over a lake
/// still holds what it needs without the shore's cells filling up to the
/// quota's cap. A share of 0 is no fill. `share` `None`: [`USABLE_SHARE`]
/// for a mission; without one, [`USABLE_SHARE`] on a finest level whose
/// ortho is too coarse for the envelope's finest cameras (its cells are
/// already half a footprint, the least [`spacing_shares`] gives, and a low
/// camera's view still holds few of them), none elsewhere (the envelope's
/// cameras see several times the landmarks they need there).
pub fn fill_windows(
    levels: &[LevelSpec],
    range: &GsdRange,
    mission: Option<&Mission>,
    share: Option<f64>,
) -> Vec<FillWindow> {
    let Some(m) = mission else {
        return widest_spans(levels, range)
            .into_iter()
            .map(|span| FillWindow::view(share.unwrap_or(if too_coarse(span) { USABLE_SHARE } else { 0.0 })))
            .collect();
    };
    let share = share.unwrap_or(USABLE_SHARE);
    widest_spans(levels, range)
        .into_iter()
        .map(|span| {
            let cell = span * m.spacing_share(span);
            let (cols, rows) = (m.width_px as f64 / cell, m.height_px as f64 / cell);
            if cols * rows <= CELLS_IN_VIEW {
                return FillWindow::view(share);
            }
            FillWindow {
                cols: (cols.round() as usize).max(VIEW_CELLS.0),
                rows: (rows.round() as usize).max(VIEW_CELLS.1),
                share: share * CELLS_IN_VIEW / (cols * rows),
            }
        })
        .collect()
}

/// Camera resolutions the ladder serves (each level within
/// [`MIN_SPAN_PX`]..[`MAX_SPAN_PX`]).
pub fn served(levels: &[LevelSpec]) -> Option<GsdRange> {
    Some(GsdRange {
        finest_m: levels.first()?.serves().finest_m,
        coarsest_m: levels.last()?.serves().coarsest_m,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_ladder_on_a_30_m_ortho() {
        let r = GsdRange::of_envelope(&DEFAULT_ENVELOPE);
        assert!((r.finest_m - 0.6894).abs() < 1e-3, "{r:?}");
        assert!((r.coarsest_m - 288.7).abs() < 0.1, "{r:?}");
        let l = ladder(30.0, 16, 32, &r, None);
        let got: Vec<(f64, u32)> = l.iter().map(|l| (l.gsd_m, l.size_px)).collect();
        // 16 px at 30 m (480 m), then 32 px at 30, 60, 120, 240 m.
        assert_eq!(got, [(30.0, 16), (30.0, 32), (60.0, 32), (120.0, 32), (240.0, 32)]);
        // The coarsest camera: the top level spans >= TARGET/sqrt2 px.
        assert!(l[4].footprint_m() / r.coarsest_m >= TARGET_SPAN_PX / 2f64.sqrt());
        assert!(l[3].footprint_m() / r.coarsest_m < TARGET_SPAN_PX / 2f64.sqrt());
        // A 1 m ortho: 32 px at 1 m (32 m) already spans at most 48 px at the
        // finest 0.69 m/px, so no 16-px level below it.
        let l = ladder(1.0, 16, 32, &r, None);
        assert_eq!((l[0].gsd_m, l[0].size_px), (1.0, 32));
        assert!(l[0].footprint_m() / r.finest_m <= MAX_SPAN_PX);
        assert!(l[0].footprint_m() / 2.0 / r.finest_m < TARGET_SPAN_PX);
        assert_eq!((l.last().unwrap().gsd_m, l.len()), (256.0, 9));
    }

    #[test]
    fn every_served_resolution_has_a_level_within_the_span_limits() {
        for (base, lo, hi) in [(1.0, 0.69, 289.0), (30.0, 10.0, 25.0), (0.5, 3.0, 300.0), (8.0, 0.1, 5000.0)]
        {
            let r = GsdRange { finest_m: lo, coarsest_m: hi };
            let l = ladder(base, 16, 32, &r, None);
            for w in l.windows(2) {
                assert!((w[1].footprint_m() / w[0].footprint_m() - 2.0).abs() < 1e-12);
                assert!(w[1].gsd_m >= w[0].gsd_m);
            }
            for s in &l {
                assert!((12..=32).contains(&s.size_px) && s.gsd_m >= base, "{s:?}");
                assert!((s.gsd_m / base - 2f64.powi(s.gsd_step as i32)).abs() < 1e-12);
            }
            // Brute force over the served range: the navigator's choice (closest to
            // TARGET in ratio) spans MIN..MAX pixels, wherever the ortho allows.
            let served = served(&l).unwrap();
            let n = 400;
            for i in 0..=n {
                let g = lo * (hi / lo).powf(i as f64 / n as f64);
                let best = l
                    .iter()
                    .min_by(|a, b| {
                        let m = |x: &LevelSpec| (x.footprint_m() / g / TARGET_SPAN_PX).ln().abs();
                        m(a).total_cmp(&m(b))
                    })
                    .unwrap();
                let span = best.footprint_m() / g;
                if g >= served.finest_m && g <= served.coarsest_m {
                    assert!((MIN_SPAN_PX..=MAX_SPAN_PX).contains(&span), "base {base} g {g}: {span} px");
                }
                // Finer than the ortho can serve: the finest level, too big, is chosen.
                if g < served.finest_m {
                    assert_eq!(best.level, 0);
                }
            }
            if lo * 16.0 * 1.5 >= base * 16.0 {
                assert!(served.finest_m <= lo, "base {base}: {served:?}");
            }
            assert!(served.coarsest_m >= hi || l.len() == 12, "base {base}: {served:?}");
        }
    }

    #[test]
    fn explicit_levels_and_one_size() {
        let r = GsdRange { finest_m: 1.0, coarsest_m: 1.0 };
        let l = ladder(2.0, 32, 32, &r, Some(3));
        let got: Vec<(f64, u32)> = l.iter().map(|l| (l.gsd_m, l.size_px)).collect();
        assert_eq!(got, [(2.0, 32), (4.0, 32), (8.0, 32)]);
        // Half the largest size is below the smallest: one size.
        assert!(ladder(2.0, 12, 16, &r, Some(2)).iter().all(|l| l.size_px == 16));
        // 24 px: 12-px native templates first, for a camera finer than the ortho.
        let fine = GsdRange { finest_m: 0.5, coarsest_m: 1.0 };
        let l = ladder(2.0, 12, 24, &fine, Some(3));
        assert_eq!(
            l.iter().map(|l| (l.gsd_m, l.size_px)).collect::<Vec<_>>(),
            [(2.0, 12), (2.0, 24), (4.0, 24)]
        );
    }

    #[test]
    fn mission_range_follows_height_and_view_angle() {
        let m = Mission {
            width_px: 200,
            height_px: 150,
            fx: 300.0,
            fy: 300.0,
            altitude_min_m: 3_000.0,
            altitude_max_m: 9_000.0,
            max_off_nadir_deg: 0.0,
        };
        // Half diagonal: atan(125 / 300).
        assert!((m.max_view_deg() - (125f64 / 300.0).atan().to_degrees()).abs() < 1e-9);
        let r = m.gsd_range();
        assert!((r.finest_m - 10.0).abs() < 1e-9);
        let cos = (125f64 / 300.0).atan().cos();
        assert!((r.coarsest_m - 30.0 / cos.powf(1.5)).abs() < 1e-9);
        let tilted = Mission { max_off_nadir_deg: 80.0, ..m };
        assert_eq!(tilted.max_view_deg(), MAX_VIEW_DEG);
        // 200x150 at 45 px per footprint: 14.8 footprints, cells of half one (the floor).
        let widest = TARGET_SPAN_PX * 2f64.sqrt();
        assert_eq!(m.spacing_share(widest), 0.5);
        // 1024x768: 384 footprints would give 120 cells of 1.8 footprints;
        // one footprint, as the default database, is the coarsest.
        let big = Mission { width_px: 1024, height_px: 768, ..m };
        let share = big.spacing_share(widest);
        let cells = (1024.0 / widest) * (768.0 / widest) / (share * share);
        assert!(share == 1.0 && (cells - 384.0).abs() < 0.5, "{share} {cells}");
        // 320x240: 37.5 footprints -> 120 cells of 0.56 footprints.
        let mid = Mission { width_px: 320, height_px: 240, ..m };
        let share = mid.spacing_share(widest);
        let cells = (320.0 / widest) * (240.0 / widest) / (share * share);
        assert!((cells - CELLS_IN_VIEW).abs() < 0.5 && share > 0.5 && share < 0.6, "{share} {cells}");
        // Per level: the 30 m ortho cannot serve the 200x150 camera's 10 m/px
        // (its finest level spans 48 px there), the others span 45 px at most.
        let r = m.gsd_range();
        let l = ladder(30.0, 12, 32, &r, None);
        let s = spacing_shares(&l, &r, Some(&m));
        assert!(s.iter().all(|&x| x == 0.5), "{s:?}");
        let sm = spacing_shares(&l, &r, Some(&mid));
        assert!(sm[0] < sm[1] && (sm[1] - share).abs() < 1e-12, "{sm:?}");
        let sb = spacing_shares(&l, &r, Some(&big));
        assert!(sb.iter().all(|&x| x == 1.0), "{sb:?}");
        // The fill: the small and the mid cameras see about 120 cells or
        // fewer: 13 x 9 and the share asked for; the large one sees 22.6 x
        // 17 cells, and aims at as many landmarks as 0.7 of 120.
        for cam in [&m, &mid] {
            let f = fill_windows(&l, &r, Some(cam), Some(0.7));
            assert!(f.iter().all(|&w| w == FillWindow::view(0.7)), "{f:?}");
        }
        let f = fill_windows(&l, &r, Some(&big), Some(0.7));
        for w in &f[1..] {
            assert_eq!((w.cols, w.rows), (23, 17));
            assert!((w.share * 384.0 - 0.7 * CELLS_IN_VIEW).abs() < 1e-9, "{w:?}");
        }
        // Without a mission: one footprint, half one where the ortho is too coarse.
        let env = GsdRange::of_envelope(&DEFAULT_ENVELOPE);
        let l = ladder(30.0, 12, 32, &env, None);
        let s = spacing_shares(&l, &env, None);
        assert_eq!(s[0], 0.5);
        assert!(s[1..].iter().all(|&x| x == 1.0), "{s:?}");
        // Sub-metre imagery: 32 m footprints are only picked by cameras that see
        // at least 705 m across (20 degrees from 2 km): 22 x 16.5 footprints,
        // so cells of 1.74 footprints still give 120.
        let l = ladder(0.5, 12, 32, &env, None);
        let s = spacing_shares(&l, &env, None);
        assert!((l[0].footprint_m() - 32.0).abs() < 1e-9 && (s[0] - 1.742).abs() < 1e-3, "{s:?}");
        assert!(s[1..].iter().all(|&x| x == 1.0), "{s:?}");
    }

    /// Without a mission, the density fill is on where the cells cannot
    /// shrink further: the finest level of an ortho too coarse for the
    /// envelope's finest cameras (the level whose cells are half a
    /// footprint), and off elsewhere; a share asked for applies everywhere.
    #[test]
    fn envelope_fill_only_where_the_ortho_is_too_coarse() {
        let env = GsdRange::of_envelope(&DEFAULT_ENVELOPE);
        for base in [0.5, 1.0, 5.0, 30.0] {
            let l = ladder(base, 16, 32, &env, None);
            let shares = spacing_shares(&l, &env, None);
            let f = fill_windows(&l, &env, None, None);
            assert_eq!(f.len(), l.len());
            for (k, (&fill, &share)) in f.iter().zip(&shares).enumerate() {
                let want = if share == 0.5 { USABLE_SHARE } else { 0.0 };
                assert_eq!(fill, FillWindow::view(want), "base {base} level {k}: spacing share {share}");
            }
            let asked = fill_windows(&l, &env, None, Some(0.4));
            assert!(asked.iter().all(|&w| w == FillWindow::view(0.4)), "{asked:?}");
            let off = fill_windows(&l, &env, None, Some(0.0));
            assert!(off.iter().all(|w| w.share == 0.0), "{off:?}");
        }
        // The 30 m ortho's finest level (16 px, 480 m) fills; a 1 m ortho's
        // finest (32 px at 1 m spans 46 px at the finest 0.69 m) does not.
        let fill_of = |base: f64| fill_windows(&ladder(base, 16, 32, &env, None), &env, None, None);
        assert_eq!(fill_of(30.0)[0].share, USABLE_SHARE);
        assert!(fill_of(30.0)[1..].iter().all(|w| w.share == 0.0));
        assert!(fill_of(1.0).iter().all(|w| w.share == 0.0));
    }

    /// Brute force over the default envelope's cameras: the cells in view of
    /// the level a navigator picks never drop below [`CELLS_IN_VIEW`], nor
    /// below what one-footprint cells give where those give fewer.
    #[test]
    fn envelope_spacing_keeps_every_camera_in_cells() {
        let env = GsdRange::of_envelope(&DEFAULT_ENVELOPE);
        for base in [0.3, 0.5, 1.0, 2.0, 5.0, 30.0] {
            let l = ladder(base, 16, 32, &env, None);
            let shares = spacing_shares(&l, &env, None);
            let mut checked = 0;
            for width_px in [160u32, 200, 320, 480, 640, 800, 1024] {
                for hfov_deg in [20.0, 25.0, 30.0, 40.0, 50.0, 60.0] {
                    for altitude_m in [2_000.0, 2_500.0, 4_000.0, 8_000.0, 15_000.0, 40_000.0] {
                        let cam = CameraSpan { width_px, hfov_deg, altitude_m };
                        let g = cam.nadir_gsd_m();
                        let (k, best) = l
                            .iter()
                            .enumerate()
                            .min_by(|a, b| {
                                let m = |x: &LevelSpec| (x.footprint_m() / g / TARGET_SPAN_PX).ln().abs();
                                m(a.1).total_cmp(&m(b.1))
                            })
                            .unwrap();
                        let span = best.footprint_m() / g;
                        if span > MAX_SPAN_PX {
                            continue; // finer than the ortho serves
                        }
                        let cells = |share: f64| {
                            let across = width_px as f64 / (span * share);
                            across * across * 0.75
                        };
                        let want = cells(1.0).min(CELLS_IN_VIEW) * 0.999;
                        assert!(
                            cells(shares[k]) >= want,
                            "base {base} {cam:?}: level {k} share {} -> {} cells",
                            shares[k],
                            cells(shares[k])
                        );
                        checked += 1;
                    }
                }
            }
            assert!(checked > 100, "{checked}");
        }
    }
}

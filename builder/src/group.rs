//! One ortho group's selection: the level plan per pyramid level, the tiling,
//! and the tile worker. Tiles of a pyramid level run in parallel, each on its
//! thread's GDAL handles ([`Worker`]); each reads its window (from the ortho,
//! or from the previous pyramid level's file), writes its half-resolution
//! copy for the next level, and cuts the templates of every level planned
//! there ([`run_tile`], returning a [`TileOutput`]).

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

use rayon::prelude::*;
use tracing::info;
use trn_landmark::lighting::SunLight;
use trn_landmark::{GeoBox, Template};

use crate::extract::{self, ExtractParams, Reject, WindowGeo};
use crate::lighting::{self, SunGrid};
use crate::pyramid::{self, LevelFile};
use crate::select::{self, CellStats, Core, Fill, LumWindow, SelectParams};
use crate::sizing::{self, LevelSpec};
use crate::terrain::{self, DemSampler, DemSpec};
use crate::{BuildCtx, BuildError, BuildOptions, LevelTally, OrthoGroup, Progress, Result, FILL_MAX_BOOST};
use trn_raster::ortho::{self, OrthoReader, Window};
use trn_raster::source::Wgs84Transform;

/// Per-thread GDAL state for one group.
struct Worker {
    ortho: OrthoReader,
    dem: DemSampler,
    to_wgs: Wgs84Transform,
    /// Buffers reused tile after tile: no allocation and no fresh pages per tile.
    win: Window,
    select: select::Scratch,
    down_lum: Vec<f32>,
    down_valid: Vec<u8>,
}

// SAFETY: GDAL datasets and OGR coordinate transformations may move between
// threads as long as one thread uses them at a time; each Worker lives in its
// own Mutex slot and is only touched while that lock is held.
unsafe impl Send for Worker {}

impl Worker {
    fn new(g: &OrthoGroup, dems: &[DemSpec]) -> Result<Self> {
        Ok(Self {
            ortho: OrthoReader::open(&g.path, &g.lum)?,
            dem: DemSampler::open(dems)?,
            to_wgs: Wgs84Transform::to_wgs84(&g.path)?,
            win: Window::default(),
            select: select::Scratch::default(),
            down_lum: Vec::new(),
            down_valid: Vec::new(),
        })
    }
}

/// One template level as processed on a pyramid level of a group.
#[derive(Clone, Copy)]
struct LevelPlan {
    /// Index of the level in the ladder.
    index: usize,
    level: u8,
    /// Pyramid level of the group it runs on (2^p native pixels per pixel).
    pyramid_level: usize,
    gsd_m: f64,
    size_px: u32,
    select: SelectParams,
}

impl LevelPlan {
    /// Pixels a tile's window reaches past its core on each side.
    fn margin(&self) -> usize {
        (self.select.win_w.max(self.select.win_h) as f64 * 0.75).ceil() as usize
            + self.select.search_radius
            + 4
    }
}

/// The level plans of a group, per pyramid level (index p: 2^p native pixels
/// per pixel), from the first pyramid level whose pixels are at most as coarse
/// as the ladder's finest step to the coarsest step's.
fn level_plans(
    opts: &BuildOptions,
    g: &OrthoGroup,
    base_gsd: f64,
    specs: &[LevelSpec],
) -> Vec<Vec<LevelPlan>> {
    let native = g.info.pixel_dx_m.max(g.info.pixel_dy_m);
    let offset = ((base_gsd / native).log2() + 1e-9).floor().max(0.0) as usize;
    let top = offset + specs.iter().map(|s| s.gsd_step as usize).max().unwrap_or(0);
    let shares = sizing::spacing_shares(specs, &opts.gsd_range(), opts.mission.as_ref());
    let fills = opts.fill_windows(specs);
    let plans_for = |p: usize| -> Vec<LevelPlan> {
        let Some(step) = p.checked_sub(offset) else { return Vec::new() };
        let scale = 2f64.powi(p as i32);
        let (px_w, px_h) = (g.info.pixel_dx_m * scale, g.info.pixel_dy_m * scale);
        specs
            .iter()
            .enumerate()
            .filter(|(_, s)| s.gsd_step as usize == step)
            .map(|(index, s)| {
                let (t, gsd) = (s.size_px as f64, s.gsd_m);
                let sp = opts.spacing(s.size_px, shares[index]) as f64 * gsd;
                LevelPlan {
                    index,
                    level: s.level,
                    pyramid_level: p,
                    gsd_m: gsd,
                    size_px: s.size_px,
                    select: SelectParams {
                        win_w: (t * gsd / px_w).round().max(4.0) as usize,
                        win_h: (t * gsd / px_h).round().max(4.0) as usize,
                        cell_w: (sp / px_w).round().max(2.0) as usize,
                        cell_h: (sp / px_h).round().max(2.0) as usize,
                        per_cell: opts.per_cell,
                        fill: (fills[index].share > 0.0).then_some(Fill {
                            share: fills[index].share as f32,
                            window_w: fills[index].cols,
                            window_h: fills[index].rows,
                            max_boost: FILL_MAX_BOOST,
                        }),
                        min_shi_tomasi: opts.min_shi_tomasi,
                        min_contrast_std: opts.min_contrast_std,
                        max_saturated: opts.max_saturated,
                        search_radius: (opts.search_radius_px as f64 * gsd / px_w.min(px_h)).round().max(2.0)
                            as usize,
                        max_second_peak: opts.max_second_peak,
                    },
                }
            })
            .collect()
    };
    (0..=top).map(plans_for).collect()
}

/// A tile: the window pixels it owns on its pyramid level (half-open).
#[derive(Clone, Copy, Debug)]
struct Tile {
    x0: usize,
    x1: usize,
    y0: usize,
    y1: usize,
}

/// Tiles per pyramid level: a whole number of the largest cell of the levels
/// cut there, about 1024 x 512 pixels.
struct Tiling {
    sizes: Vec<(usize, usize)>,
    dims: Vec<(usize, usize)>,
}

impl Tiling {
    fn new(g: &OrthoGroup, plans: &[Vec<LevelPlan>]) -> Self {
        let sizes = (0..plans.len()).map(|p| (g.info.width >> p, g.info.height >> p)).collect();
        let round = |cell: usize, target: usize| {
            let mut n = target.div_ceil(cell).max(1);
            if (n * cell) % 2 == 1 {
                n += 1;
            }
            n * cell
        };
        let dims = plans
            .iter()
            .map(|ps| {
                let cw = ps.iter().map(|l| l.select.cell_w).max().unwrap_or(2);
                let ch = ps.iter().map(|l| l.select.cell_h).max().unwrap_or(2);
                (round(cw, 1024), round(ch, 512))
            })
            .collect();
        Self { sizes, dims }
    }

    fn tiles(&self, p: usize) -> Vec<Tile> {
        let ((w, h), (tw, th)) = (self.sizes[p], self.dims[p]);
        let mut v = Vec::new();
        for y0 in (0..h).step_by(th) {
            for x0 in (0..w).step_by(tw) {
                v.push(Tile { x0, x1: (x0 + tw).min(w), y0, y1: (y0 + th).min(h) });
            }
        }
        v
    }
}

/// What one level's selection made of one tile.
struct TileLevel {
    /// Index of the level in the ladder.
    index: usize,
    cells: CellStats,
    rejected: HashMap<Reject, usize>,
    /// Sum of the landmarks' shading shares.
    shading_sum: f64,
}

/// What one tile gives: its templates, and per level cut there, its tally.
struct TileOutput {
    templates: Vec<Template>,
    levels: Vec<TileLevel>,
}

/// What every tile of a group shares.
struct GroupCtx<'a> {
    opts: &'a BuildOptions,
    g: &'a OrthoGroup,
    suns: &'a [SunGrid],
}

/// One pyramid level's pass: where its windows come from and where its
/// half-resolution copy goes.
struct Pass<'a> {
    plans: &'a [LevelPlan],
    margin: usize,
    /// The previous pyramid level's file (`None`: the ortho itself).
    prev: Option<&'a LevelFile>,
    /// The next pyramid level's file (`None` on the last level).
    next: Option<&'a LevelFile>,
}

/// Selects over one ortho group, streaming templates to `sink`; the tallies
/// per level of the ladder.
pub(crate) fn build_group(
    ctx: &BuildCtx,
    g: &OrthoGroup,
    sink: &(dyn Fn(Vec<Template>) -> Result<()> + Sync),
) -> Result<Vec<LevelTally>> {
    let BuildCtx { opts, dems, suns, base_gsd, specs, work, cancel, progress } = *ctx;
    let plans = level_plans(opts, g, base_gsd, specs);
    let mut tallies = vec![LevelTally::default(); specs.len()];
    for l in plans.iter().flatten() {
        let scale = 2f64.powi(l.pyramid_level as i32);
        let (dx, dy) = (g.info.pixel_dx_m * scale, g.info.pixel_dy_m * scale);
        tallies[l.index].cell_area_m2 = l.select.cell_w as f64 * dx * l.select.cell_h as f64 * dy;
    }
    let tiling = Tiling::new(g, &plans);
    let total: usize = (0..plans.len()).map(|p| tiling.tiles(p).len()).sum();
    let first = g.files[0].file_name().unwrap_or_default().to_string_lossy().into_owned();
    let more = if g.files.len() > 1 { format!(" +{}", g.files.len() - 1) } else { String::new() };
    progress(Progress::Group { label: &format!("{first}{more}"), tiles: total as u64 });

    // One set of GDAL/PROJ handles per thread: opening them costs milliseconds.
    let workers: Vec<Mutex<Option<Worker>>> =
        (0..rayon::current_num_threads().max(1)).map(|_| Mutex::new(None)).collect();
    let margin_of = |p: usize| plans[p].iter().map(LevelPlan::margin).max().unwrap_or(0);
    // A mosaic's VRT caches its own blocks and its files' (and a warped
    // source's, the warper's source windows): three layers, with blocks of up
    // to 512 rows assumed where the files' are unknown here.
    let window_h = tiling.dims[0].1 + 2 * margin_of(0);
    let _cache = if g.files.len() == 1 {
        ortho::ortho_cache_bytes(&g.path, window_h, workers.len())
    } else {
        ortho::ortho_cache_bytes(&g.path, window_h.div_ceil(512) * 512, workers.len()).map(|b| 3 * b)
    }
    .map(ortho::CacheLimit::new);
    let group_ctx = GroupCtx { opts, g, suns };
    let mut prev: Option<LevelFile> = None;
    for p in 0..plans.len() {
        let next = if p + 1 < plans.len() {
            let (w, h) = tiling.sizes[p];
            Some(LevelFile::create(work, &format!("g{}-p{}", g.index, p + 1), w / 2, h / 2)?)
        } else {
            None
        };
        let pass = Pass { plans: &plans[p], margin: margin_of(p), prev: prev.as_ref(), next: next.as_ref() };
        let outputs = run_tiles(&tiling.tiles(p), &workers, sink, |worker, tile| {
            if cancel.load(Ordering::Relaxed) {
                return Err(BuildError::Cancelled);
            }
            let worker = match worker {
                Some(w) => w,
                None => worker.insert(Worker::new(g, dems)?),
            };
            let out = run_tile(&group_ctx, worker, &pass, tile)?;
            progress(Progress::Tile);
            Ok(out)
        })?;
        for levels in outputs {
            for l in levels {
                tallies[l.index].add(l.cells, l.rejected, l.shading_sum);
            }
        }
        for l in pass.plans {
            let names: Vec<String> = g.files.iter().map(|f| f.display().to_string()).collect();
            info!(
                "level {} ({} px at {:.2} m): {} templates from {}",
                l.level,
                l.size_px,
                l.gsd_m,
                tallies[l.index].cells.taken,
                names.join(", ")
            );
        }
        prev = next;
    }
    progress(Progress::GroupDone);
    Ok(tallies)
}

/// Runs `tiles` in parallel (rayon's split, which keeps a thread on
/// neighbouring tiles, whose blocks its GDAL handle has cached) and hands
/// every tile's templates to `sink` in tile order: a tile finished before
/// those ahead of it waits for them (measured: +3-4% peak memory on the
/// 100-megapixel benchmark, no time), so the database's ids follow the tiles,
/// whichever thread finished first, and are the same for any number of
/// threads. Returns each tile's levels in tile order; after an error the
/// tiles not yet started are skipped and the first error in tile order is
/// returned.
fn run_tiles(
    tiles: &[Tile],
    workers: &[Mutex<Option<Worker>>],
    sink: &(dyn Fn(Vec<Template>) -> Result<()> + Sync),
    run: impl Fn(&mut Option<Worker>, Tile) -> Result<TileOutput> + Sync,
) -> Result<Vec<Vec<TileLevel>>> {
    let failed = AtomicBool::new(false);
    let in_order = Mutex::new(InOrder::default());
    let done: Vec<Option<Result<Vec<TileLevel>>>> = (0..tiles.len())
        .into_par_iter()
        .map(|i| {
            if failed.load(Ordering::Relaxed) {
                return None;
            }
            let slot = &workers[rayon::current_thread_index().unwrap_or(0) % workers.len()];
            let mut worker = slot.lock().unwrap_or_else(|e| e.into_inner());
            let levels = run(&mut worker, tiles[i]).and_then(|out| {
                in_order.lock().unwrap_or_else(|e| e.into_inner()).push(i, out.templates, sink)?;
                Ok(out.levels)
            });
            if levels.is_err() {
                failed.store(true, Ordering::Relaxed);
            }
            Some(levels)
        })
        .collect();
    done.into_iter().flatten().collect()
}

/// Tiles' templates waiting for the tiles before them ([`run_tiles`]).
#[derive(Default)]
struct InOrder {
    /// The first tile not yet handed on.
    next: usize,
    waiting: BTreeMap<usize, Vec<Template>>,
}

impl InOrder {
    /// Takes tile `i`'s templates and hands on every tile now in order.
    fn push(
        &mut self,
        i: usize,
        templates: Vec<Template>,
        sink: &(dyn Fn(Vec<Template>) -> Result<()> + Sync),
    ) -> Result<()> {
        self.waiting.insert(i, templates);
        while let Some(t) = self.waiting.remove(&self.next) {
            self.next += 1;
            if !t.is_empty() {
                sink(t)?;
            }
        }
        Ok(())
    }
}

/// One tile of a pass: reads its window, writes its half-resolution copy to
/// the next pyramid level, and cuts the templates of every level planned on
/// this one.
fn run_tile(ctx: &GroupCtx, worker: &mut Worker, pass: &Pass, tile: Tile) -> Result<TileOutput> {
    let Tile { x0, x1, y0, y1 } = tile;
    let margin = pass.margin;
    let (wx0, wy0) = (x0 as isize - margin as isize, y0 as isize - margin as isize);
    let (ww, wh) = (x1 - x0 + 2 * margin, y1 - y0 + 2 * margin);
    let mut win = std::mem::take(&mut worker.win);
    match pass.prev {
        None => worker.ortho.read_into(wx0, wy0, ww, wh, &mut win)?,
        Some(f) => f.read_into(wx0, wy0, ww, wh, &mut win)?,
    };
    if let Some(next) = pass.next {
        let (cw, ch) = ((x1 - x0) & !1, (y1 - y0) & !1);
        let nw = (cw / 2).min(next.width.saturating_sub(x0 / 2));
        if nw > 0 && ch > 0 {
            let rows = (ch / 2).min(next.height.saturating_sub(y0 / 2));
            let (lum, valid) = (&mut worker.down_lum, &mut worker.down_valid);
            pyramid::downsample2_into(&win, margin, margin, nw, rows, lum, valid);
            next.write(x0 / 2, y0 / 2, nw, lum, valid)?;
        }
    }
    let mut scratch = std::mem::take(&mut worker.select);
    let mut out = TileOutput { templates: Vec::new(), levels: Vec::with_capacity(pass.plans.len()) };
    for l in pass.plans {
        let core = Core { x0: margin, x1: margin + (x1 - x0), y0: margin, y1: margin + (y1 - y0) };
        let level = tile_templates(ctx, worker, &win, core, l, &mut scratch, &mut out.templates);
        out.levels.push(level);
    }
    (worker.win, worker.select) = (win, scratch);
    Ok(out)
}

/// Selects and cuts one level's templates on one tile's window (appended to
/// `out`, once per sun of `ctx.suns` when there are any); a cell whose best
/// candidate is refused at extraction takes the next.
fn tile_templates(
    ctx: &GroupCtx,
    worker: &Worker,
    win: &Window,
    core: Core,
    plan: &LevelPlan,
    scratch: &mut select::Scratch,
    out: &mut Vec<Template>,
) -> TileLevel {
    let GroupCtx { opts, g, suns } = *ctx;
    let share_suns: &[SunLight] = if opts.suns.is_empty() { &lighting::SHARE_SUNS } else { &opts.suns };
    let mut shading_sum = 0.0;
    let img = LumWindow { width: win.width, height: win.height, lum: &win.lum, valid: &win.valid };
    let scale = 2f64.powi(plan.pyramid_level as i32);
    let geo = WindowGeo { to_crs: g.info.to_crs, scale, to_wgs: &worker.to_wgs };
    let ep = ExtractParams {
        level: plan.level,
        gsd_m: plan.gsd_m,
        size_px: plan.size_px,
        height_grid_n: opts.height_grid_n,
        max_plane_residual_m: opts.max_relief_gsd.map(|r| r * plan.gsd_m),
        max_view_deg: opts.max_view_deg(),
        max_hidden_share: opts.max_hidden_share,
        source: g.index,
    };
    let mut rejected: HashMap<Reject, usize> = HashMap::new();
    // The DEM under the whole window, read once for all its templates (on the
    // first candidate: most tiles of water or nodata have none).
    let mut patch: Option<Option<terrain::DemPatch>> = None;
    let mut accept = |c: &select::Candidate| -> bool {
        let p = patch.get_or_insert_with(|| window_dem_patch(win, &geo, &worker.dem));
        let got = match p {
            Some(p) => extract::extract(win, &geo, p, c, &ep),
            None => extract::extract(win, &geo, &worker.dem, c, &ep),
        };
        match got {
            Ok(mut t) => {
                // Exact integer sums of the bytes, then the moments.
                let n = t.pixels.len().max(1) as f64;
                let (sum, sum_sq) = t
                    .pixels
                    .iter()
                    .fold((0u64, 0u64), |(s, q), &v| (s + v as u64, q + (v as u64) * (v as u64)));
                let mean = sum as f64 / n;
                let std = (sum_sq as f64 / n - mean * mean).max(0.0).sqrt();
                t.quality.shading_share =
                    lighting::shading_share(&t.terrain.height_grid, mean, std, share_suns);
                if opts.max_shading_share.is_some_and(|m| t.quality.shading_share as f64 > m) {
                    *rejected.entry(Reject::Shading).or_default() += 1;
                    return false;
                }
                shading_sum += t.quality.shading_share as f64;
                if suns.is_empty() {
                    out.push(t);
                } else {
                    for (k, sun) in suns.iter().enumerate() {
                        out.push(Template { pixels: sun.relight(&t), lighting: k as u8 + 1, ..t.clone() });
                    }
                }
                true
            }
            Err(r) => {
                *rejected.entry(r).or_default() += 1;
                false
            }
        }
    };
    let cells = select::select_with(&img, &plan.select, core, scratch, &mut accept);
    TileLevel { index: plan.index, cells, rejected, shading_sum }
}

/// The DEM under a whole window and a margin around it (`None` where the
/// window's outline does not transform).
fn window_dem_patch<'d>(
    win: &Window,
    geo: &WindowGeo<'_>,
    dem: &'d DemSampler,
) -> Option<terrain::DemPatch<'d>> {
    let (w, h) = (win.width as f64 - 1.0, win.height as f64 - 1.0);
    let outline: Vec<(f64, f64)> = (0..=8)
        .flat_map(|i| {
            let f = i as f64 / 8.0;
            [(w * f, 0.0), (w * f, h), (0.0, h * f), (w, h * f)]
        })
        .collect();
    let b = geo.lonlat(win, &outline).and_then(GeoBox::around)?;
    // A margin for the tangent plane's reach past the window's outline.
    let (mx, my) = (0.05 * (b.max_lon_deg - b.min_lon_deg), 0.05 * (b.max_lat_deg - b.min_lat_deg));
    Some(dem.patch(&GeoBox::new(
        b.min_lon_deg - mx,
        b.min_lat_deg - my,
        b.max_lon_deg + mx,
        b.max_lat_deg + my,
    )))
}

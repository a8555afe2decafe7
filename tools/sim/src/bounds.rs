//! Local bounds of the terrain for the ray marcher: a max-height pyramid
//! ("max mipmap") whose blocks also hold their own steepest slope.
//!
//! Level `k` cuts the height grid into square blocks of `side` cells. Block
//! `(i, j)` *owns* the grid positions `row in [i side, (i + 1) side)`,
//! `col in [j side, (j + 1) side)`, and its bounds hold over its *reach*: the
//! owned square grown by one cell on every side. Over the reach the bilinear
//! surface (each cell a convex combination of its four nodes) is at most
//! `max_h`, and its gradient is at most `slope` (rise over ground run). A
//! ray that starts in the owned square and moves less than half a cell
//! (in grid units) away from its straight-line prediction stays in the reach
//! until it has crossed half a cell into the next block: that margin is what
//! lets the marcher predict the block's exit linearly on a lat/lon grid.
//!
//! Where the DEM has no data the renderer's floor is `h_min_m`, so no-data
//! nodes count as `h_min_m` for the maximum; a block reaching a no-data node
//! has an infinite slope (from the floor up to the DEM is a cliff that no
//! slope between valid nodes bounds). Past the grid's edge the floor lies
//! below every node: a ray leaving the grid only sees the surface drop.
//! Pure math on the height grid: no I/O.

use trn_landmark::grid::LatLonGrid;

/// Cells per block side, finest level first: a fine level to skip close
/// over ridges, coarser ones to cross valleys and descend from high above.
pub const BLOCK_SIDES: [usize; 3] = [8, 32, 128];

/// Bounds over one block's reach.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Block {
    /// Largest terrain height (m), no-data counting as the floor.
    pub max_h: f32,
    /// Largest slope (rise over ground run) of the bilinear surface;
    /// infinite where the reach meets no data.
    pub slope: f32,
}

/// One level of the pyramid.
#[derive(Clone, Debug)]
pub struct BlockLevel {
    /// Cells per block side.
    pub side: usize,
    pub block_rows: usize,
    pub block_cols: usize,
    /// The grid's last row and column.
    max_row: f64,
    max_col: f64,
    blocks: Vec<Block>,
}

/// Grid-coordinate box (inclusive): where a step must land.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridBox {
    pub row0: f64,
    pub row1: f64,
    pub col0: f64,
    pub col1: f64,
}

impl GridBox {
    #[inline(always)]
    pub fn contains(&self, row: f64, col: f64) -> bool {
        row >= self.row0 && row <= self.row1 && col >= self.col0 && col <= self.col1
    }
}

impl BlockLevel {
    /// The block owning grid position (row, col) and its index; `None`
    /// outside the grid.
    #[inline(always)]
    pub fn block_at(&self, row: f64, col: f64) -> Option<(usize, usize, Block)> {
        if !(row >= 0.0 && col >= 0.0 && row <= self.max_row && col <= self.max_col) {
            return None;
        }
        // Truncation is the floor here (non-negative); the grid's last
        // row/column belongs to the last block.
        let (i, j) = ((row as usize) / self.side, (col as usize) / self.side);
        let (i, j) = (i.min(self.block_rows - 1), j.min(self.block_cols - 1));
        Some((i, j, self.blocks[i * self.block_cols + j]))
    }

    /// The reach of block (i, j): the box where its bounds hold.
    #[inline(always)]
    pub fn reach(&self, i: usize, j: usize) -> GridBox {
        let s = self.side as f64;
        GridBox {
            row0: i as f64 * s - 1.0,
            row1: (i + 1) as f64 * s + 1.0,
            col0: j as f64 * s - 1.0,
            col1: (j + 1) as f64 * s + 1.0,
        }
    }
}

/// The pyramid of block bounds over a height grid.
#[derive(Clone, Debug)]
pub struct TerrainBounds {
    pub levels: Vec<BlockLevel>,
}

impl TerrainBounds {
    /// Builds the levels of [`BLOCK_SIDES`] over `heights`, with `h_min` the
    /// floor where there is no data.
    pub fn new(heights: &LatLonGrid<f32>, h_min: f64) -> Self {
        Self::with_sides(heights, h_min, &BLOCK_SIDES)
    }

    /// [`TerrainBounds::new`] with the given block sides (cells).
    pub fn with_sides(heights: &LatLonGrid<f32>, h_min: f64, sides: &[usize]) -> Self {
        let (rows, cols, v) = (heights.rows, heights.cols, &heights.values);
        // Ground run of one cell per grid row: the smaller of its two edges'
        // (metres per degree of longitude shrink poleward).
        let runs: Vec<(f64, f64)> = (0..rows)
            .map(|r| {
                let lat = |r: usize| heights.north_lat_deg - r as f64 * heights.dlat_deg;
                let a = trn_geodesy::metres_per_degree(lat(r));
                let b = trn_geodesy::metres_per_degree(lat((r + 1).min(rows - 1)));
                (heights.dlat_deg * a.0.min(b.0), heights.dlon_deg * a.1.min(b.1))
            })
            .collect();
        // Slope of the edge between two nodes.
        let edge = |a: f32, b: f32, run: f64| ((b as f64 - a as f64) / run).abs();
        let levels = sides
            .iter()
            .map(|&side| {
                let block_rows = (rows - 1).div_ceil(side).max(1);
                let block_cols = (cols - 1).div_ceil(side).max(1);
                let mut blocks = Vec::with_capacity(block_rows * block_cols);
                for i in 0..block_rows {
                    // The nodes of the reach's cells: one more past each end.
                    let (r0, r1) = ((i * side) as isize - 1, ((i + 1) * side + 1) as isize);
                    for j in 0..block_cols {
                        let (c0, c1) = ((j * side) as isize - 1, ((j + 1) * side + 1) as isize);
                        // (Past the grid's edge the floor lies below every node.)
                        let (r0, r1) = (r0.max(0) as usize, (r1 as usize).min(rows - 1));
                        let (c0, c1) = (c0.max(0) as usize, (c1 as usize).min(cols - 1));
                        let mut max_h = h_min;
                        let mut slope = 0.0f64;
                        for r in r0..=r1 {
                            let (dy, dx) = runs[r];
                            for c in c0..=c1 {
                                let h = v[r * cols + c];
                                let east = if c < c1 { v[r * cols + c + 1] } else { h };
                                let south = if r < r1 { v[(r + 1) * cols + c] } else { h };
                                if h.is_finite() {
                                    max_h = max_h.max(h as f64);
                                }
                                slope = if h.is_nan() || east.is_nan() || south.is_nan() {
                                    f64::INFINITY
                                } else {
                                    slope.max(edge(h, east, dx)).max(edge(h, south, dy))
                                };
                            }
                        }
                        // A bilinear cell's gradient is at most sqrt(2) times
                        // its steepest edge; rounded up to f32.
                        let slope = slope * std::f64::consts::SQRT_2 * (1.0 + 1e-6);
                        blocks.push(Block { max_h: max_h as f32, slope: slope as f32 });
                    }
                }
                BlockLevel {
                    side,
                    block_rows,
                    block_cols,
                    max_row: (rows - 1) as f64,
                    max_col: (cols - 1) as f64,
                    blocks,
                }
            })
            .collect();
        Self { levels }
    }
}

/// How fast a ray can move through the grid and towards the terrain, for
/// [`TerrainBounds::step`].
#[derive(Clone, Copy, Debug)]
pub struct RayMotion {
    /// Grid velocity (rows, columns per metre of range) and its inverses.
    v_row: f64,
    v_col: f64,
    inv_v_row: f64,
    inv_v_col: f64,
    /// Upper bound of the ray's descent rate (m of height per m of range).
    d_down: f64,
    /// Upper bound of its horizontal rate (m of ground per m of range).
    d_horiz: f64,
}

impl RayMotion {
    /// The motion at grid velocity `(v_row, v_col)` (rows, columns per
    /// metre of range), with bounds of the descent and horizontal rates over
    /// the rest of the ray.
    pub fn new((v_row, v_col): (f64, f64), d_down: f64, d_horiz: f64) -> Self {
        Self {
            v_row,
            v_col,
            inv_v_row: 1.0 / v_row,
            inv_v_col: 1.0 / v_col,
            d_down: d_down.max(0.0),
            d_horiz: d_horiz.clamp(0.0, 1.0),
        }
    }

    /// Range (m) the ray takes to cross one cell along its faster axis.
    pub fn cell_crossing_m(&self) -> f64 {
        1.0 / self.v_row.abs().max(self.v_col.abs())
    }

    /// Range (m) until the linear prediction from (row, col) leaves
    /// `[lo_r, hi_r] x [lo_c, hi_c]`, which must hold the position.
    #[inline(always)]
    fn exit(&self, row: f64, col: f64, lo_r: f64, hi_r: f64, lo_c: f64, hi_c: f64) -> f64 {
        let along = |x: f64, v: f64, inv: f64, lo: f64, hi: f64| {
            if v > 0.0 {
                (hi - x) * inv
            } else if v < 0.0 {
                (lo - x) * inv
            } else {
                f64::INFINITY
            }
        };
        along(row, self.v_row, self.inv_v_row, lo_r, hi_r).min(along(
            col,
            self.v_col,
            self.inv_v_col,
            lo_c,
            hi_c,
        ))
    }
}

impl TerrainBounds {
    /// The longest step (m of range) the pyramid allows from grid position
    /// (row, col) at height `h`, `f` above the ground there (> 0), and the
    /// reach its landing point must lie in (else the linear prediction of
    /// the grid position was wrong and the step must be retaken). Per level,
    /// within the owning block's square grown by half a cell, the ray stays
    /// above the surface until it has descended to the block's maximum, and
    /// at least until it could meet a surface rising at the block's slope
    /// (sphere tracing); the longest of the levels' steps wins. `None`
    /// outside the grid.
    #[inline]
    pub fn step(&self, m: &RayMotion, row: f64, col: f64, h: f64, f: f64) -> Option<(f64, GridBox)> {
        let mut best: Option<(f64, GridBox)> = None;
        // Coarsest first: a ray clearing a whole block needs no finer look
        // (the finer blocks' squares lie inside it).
        for level in self.levels.iter().rev() {
            let (i, j, b) = level.block_at(row, col)?;
            let s = level.side as f64;
            let (r0, c0) = (i as f64 * s, j as f64 * s);
            let t_exit = m.exit(row, col, r0 - 0.5, r0 + s + 0.5, c0 - 0.5, c0 + s + 0.5);
            let over = h - b.max_h as f64;
            let t_over = if over > 0.0 { over / m.d_down } else { 0.0 };
            let slope = b.slope as f64;
            let t_sphere = if slope.is_finite() { f / (m.d_down + slope * m.d_horiz) } else { 0.0 };
            let t = t_exit.min(t_over.max(t_sphere));
            if best.is_none_or(|(tb, _)| t > tb) {
                best = Some((t, level.reach(i, j)));
            }
            if t >= t_exit {
                break;
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A rough grid with one-node spikes, a cliff and a hole of no data.
    fn grid() -> LatLonGrid<f32> {
        let (rows, cols) = (77, 90);
        let mut rng = crate::rng::Rng::stream(5, "bounds");
        let values = (0..rows * cols)
            .map(|i| {
                let (r, c) = (i / cols, i % cols);
                let mut h = 1500.0 + rng.range(-30.0, 30.0) + if c > 40 { 400.0 } else { 0.0 };
                if rng.range(0.0, 1.0) < 0.02 {
                    h += 900.0;
                }
                if (30..33).contains(&r) && (60..62).contains(&c) {
                    h = f64::NAN;
                }
                h as f32
            })
            .collect();
        LatLonGrid {
            north_lat_deg: 40.2,
            west_lon_deg: -105.7,
            dlat_deg: 0.0005,
            dlon_deg: 0.0005,
            rows,
            cols,
            values,
        }
    }

    #[test]
    fn blocks_bound_every_bilinear_height_and_slope_in_their_reach() {
        let g = grid();
        let h_min = g.values.iter().filter(|h| h.is_finite()).fold(f32::INFINITY, |a, &b| a.min(b)) as f64;
        let bounds = TerrainBounds::with_sides(&g, h_min, &[4, 8, 32]);
        let (m_lat, m_lon) = trn_geodesy::metres_per_degree(40.2);
        let mut rng = crate::rng::Rng::stream(6, "reach");
        let (mut heights, mut slopes) = (0, 0);
        for level in &bounds.levels {
            for i in 0..level.block_rows {
                for j in 0..level.block_cols {
                    let b = level.blocks[i * level.block_cols + j];
                    let reach = level.reach(i, j);
                    let inside = |r: f64, c: f64| {
                        reach.contains(r, c)
                            && r >= 0.0
                            && c >= 0.0
                            && r <= g.rows as f64 - 1.0
                            && c <= g.cols as f64 - 1.0
                    };
                    for _ in 0..300 {
                        let r = rng.range(reach.row0, reach.row1);
                        let c = rng.range(reach.col0, reach.col1);
                        if !inside(r, c) {
                            continue;
                        }
                        // No data reads as the floor.
                        let h = g.bilinear_at(r, c);
                        let h = if h.is_finite() { h } else { h_min };
                        assert!(
                            h <= b.max_h as f64,
                            "side {} block ({i}, {j}) at ({r}, {c}): {h} > {}",
                            level.side,
                            b.max_h
                        );
                        heights += 1;
                        // A second point nearby: the rise over the ground run.
                        let (r2, c2) = (r + rng.range(-1.5, 1.5), c + rng.range(-1.5, 1.5));
                        let h2 = g.bilinear_at(r2, c2);
                        if inside(r2, c2) && h2.is_finite() && g.bilinear_at(r, c).is_finite() {
                            let run = (((r2 - r) * g.dlat_deg * m_lat).powi(2)
                                + ((c2 - c) * g.dlon_deg * m_lon).powi(2))
                            .sqrt();
                            // Straight segments between valid points of valid cells only.
                            let valid = (0..=20).all(|k| {
                                let f = k as f64 / 20.0;
                                g.bilinear_at(r + f * (r2 - r), c + f * (c2 - c)).is_finite()
                            });
                            if valid && run > 1.0 {
                                assert!(
                                    (h2 - h).abs() <= b.slope as f64 * run * (1.0 + 1e-9),
                                    "side {} block ({i}, {j})",
                                    level.side
                                );
                                slopes += 1;
                            }
                        }
                    }
                    // Blocks reaching the hole have no slope bound.
                    let hole = (30..33).any(|r: usize| {
                        (60..62).any(|c: usize| {
                            reach.contains(r as f64, c as f64)
                                || reach.contains(r as f64 + 0.99, c as f64 + 0.99)
                        })
                    });
                    if hole {
                        assert!(b.slope.is_infinite());
                    }
                }
            }
        }
        assert!(heights > 20_000 && slopes > 10_000, "{heights} {slopes}");
        // The largest maximum is the grid's.
        let top = g.values.iter().filter(|h| h.is_finite()).fold(f32::NEG_INFINITY, |a, &b| a.max(b));
        assert!(bounds.levels.iter().all(|l| l.blocks.iter().any(|b| b.max_h == top)));
    }

    #[test]
    fn positions_map_to_their_owning_block() {
        let g = grid();
        let bounds = TerrainBounds::with_sides(&g, 1400.0, &[8]);
        let l = &bounds.levels[0];
        assert_eq!((l.block_rows, l.block_cols), (10, 12));
        assert_eq!(l.block_at(0.0, 0.0).map(|b| (b.0, b.1)), Some((0, 0)));
        assert_eq!(l.block_at(8.0, 15.99).map(|b| (b.0, b.1)), Some((1, 1)));
        // The last row and column belong to the last blocks.
        assert_eq!(l.block_at(76.0, 89.0).map(|b| (b.0, b.1)), Some((9, 11)));
        assert!(l.block_at(-0.01, 3.0).is_none());
        assert!(l.block_at(76.01, 3.0).is_none());
        assert!(l.block_at(3.0, f64::NAN).is_none());
    }
}

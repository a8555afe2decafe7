//! Bulk loading of SQLite R*Tree virtual tables.
//!
//! Inserting through the R*Tree module costs ~12 us per entry: every insert reads the
//! path from the root, rewrites the whole leaf blob, the rowid map and often the
//! parents. For a static set of boxes this module instead packs the tree itself (sort
//! by a caller's key, e.g. a Hilbert curve, then fill nodes in that order, the classic
//! packed R-tree) and writes the three shadow tables of the R*Tree module directly, in
//! its on-disk format (ext/rtree/rtree.c; part of SQLite's stable file format, and
//! `rtreecheck()` verifies all of it). For the float32 `rtree` module without
//! auxiliary columns:
//!
//! - `%_node(nodeno INTEGER PRIMARY KEY, data)`: node 1 is the root. Every blob is as
//!   long as the root that `CREATE VIRTUAL TABLE` wrote (the table's node size); bytes
//!   0-1 hold the tree depth (root only; 0 = the root is a leaf), bytes 2-3 the cell
//!   count, then the cells: an 8-byte rowid (leaf) or child node number, and a float32
//!   (min, max) per dimension, all big-endian; zero padding after.
//! - `%_rowid(rowid INTEGER PRIMARY KEY, nodeno)`: the leaf holding each entry.
//! - `%_parent(nodeno INTEGER PRIMARY KEY, parentnode)`: each non-root node's parent.
//!
//! Coordinates are rounded to float32 outward exactly as the module's rtreeValueDown /
//! rtreeValueUp do, so every entry's box is bit for bit what an `INSERT` would store.
//! The resulting tree is an ordinary R*Tree: later inserts and deletes through the
//! module (e.g. by GDAL's triggers) work as on any other.

use std::path::Path;

use rusqlite::Connection;

use crate::error::{SqlContext, StoreError, StoreErrorKind};

/// rtree.c's RNDTOWARDS and RNDAWAY.
const ROUND_TOWARDS_ZERO: f64 = 1.0 - 1.0 / 8_388_608.0;
const ROUND_AWAY_FROM_ZERO: f64 = 1.0 + 1.0 / 8_388_608.0;

/// A float32 at or below `d`, as the R*Tree module stores a lower bound (rtreeValueDown).
pub(crate) fn round_down(d: f64) -> f32 {
    let f = d as f32;
    if f64::from(f) > d {
        (d * if d < 0.0 { ROUND_AWAY_FROM_ZERO } else { ROUND_TOWARDS_ZERO }) as f32
    } else {
        f
    }
}

/// A float32 at or above `d`, as the R*Tree module stores an upper bound (rtreeValueUp).
pub(crate) fn round_up(d: f64) -> f32 {
    let f = d as f32;
    if f64::from(f) < d {
        (d * if d < 0.0 { ROUND_TOWARDS_ZERO } else { ROUND_AWAY_FROM_ZERO }) as f32
    } else {
        f
    }
}

/// One entry of an R*Tree with `C / 2` dimensions.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Entry<const C: usize> {
    pub id: i64,
    /// Packing order: entries are packed sorted by (key, id).
    pub key: u64,
    /// (min, max) per dimension, in column order, as stored.
    pub bounds: [f32; C],
}

impl<const C: usize> Entry<C> {
    /// The entry that `INSERT INTO rtree VALUES (id, bounds...)` would store; `Err`
    /// with the dimension whose min > max, which the module refuses too.
    pub fn new(id: i64, key: u64, bounds: [f64; C]) -> Result<Self, usize> {
        let mut stored = [0f32; C];
        for d in 0..C / 2 {
            stored[2 * d] = round_down(bounds[2 * d]);
            stored[2 * d + 1] = round_up(bounds[2 * d + 1]);
            if stored[2 * d].is_nan() || stored[2 * d + 1].is_nan() || stored[2 * d] > stored[2 * d + 1] {
                return Err(d);
            }
        }
        Ok(Self { id, key, bounds: stored })
    }
}

/// Position of a point of the unit square along a Hilbert curve of order 16; for a
/// packing order that keeps neighbours together.
pub(crate) fn hilbert_key(x: f64, y: f64) -> u64 {
    const N: u32 = 1 << 16;
    let cell = |v: f64| (v.clamp(0.0, 1.0) * f64::from(N - 1)).round() as u32;
    let (mut x, mut y) = (cell(x), cell(y));
    let mut d = 0u64;
    let mut s = N / 2;
    while s > 0 {
        let rx = u32::from(x & s != 0);
        let ry = u32::from(y & s != 0);
        d += u64::from(s) * u64::from(s) * u64::from((3 * rx) ^ ry);
        if ry == 0 {
            if rx == 1 {
                x = N - 1 - x;
                y = N - 1 - y;
            }
            std::mem::swap(&mut x, &mut y);
        }
        s /= 2;
    }
    d
}

/// One level of the tree being built: the cells (child node or entry id, box) of all
/// its nodes, in order.
struct Level<const C: usize> {
    cells: Vec<(i64, [f32; C])>,
    /// Node `j` of this level holds `cells[starts[j]..starts[j + 1]]`.
    starts: Vec<usize>,
}

/// Fills the R*Tree `table`, which must be empty (just created), with `entries`
/// (reordered). Runs inside the caller's transaction.
pub(crate) fn bulk_load<const C: usize>(
    conn: &Connection,
    path: &Path,
    table: &str,
    entries: &mut [Entry<C>],
) -> Result<(), StoreError> {
    const { assert!(C >= 2 && C & 1 == 0, "an entry holds (min, max) pairs") };
    let corrupt =
        |msg: String| StoreError::new(path, StoreErrorKind::Corrupt(format!("R*Tree {table}: {msg}")));
    let shadow = |suffix: &str| format!("\"{}{suffix}\"", table.replace('"', "\"\""));
    let columns = conn.prepare(&format!("SELECT * FROM {}", shadow(""))).at(path)?.column_count();
    let node_size: i64 = conn
        .query_row(&format!("SELECT length(data) FROM {} WHERE nodeno = 1", shadow("_node")), [], |r| {
            r.get(0)
        })
        .at(path)?;
    let filled: i64 =
        conn.query_row(&format!("SELECT count(*) FROM {}", shadow("_rowid")), [], |r| r.get(0)).at(path)?;
    let cell_bytes = 8 + 4 * C;
    let node_size = usize::try_from(node_size).unwrap_or(0);
    if columns != 1 + C || filled != 0 || node_size < 4 + 2 * cell_bytes {
        return Err(corrupt(format!(
            "not a fresh R*Tree of {} dimensions ({columns} columns, {filled} entries, node size {node_size})",
            C / 2
        )));
    }
    if entries.is_empty() {
        return Ok(());
    }
    let capacity = (node_size - 4) / cell_bytes;
    entries.sort_unstable_by_key(|e| (e.key, e.id));

    // Bottom-up: leaf cells first; each level's nodes become the next level's cells.
    // Nodes of a level share its cells evenly, so that none is nearly empty.
    let mut levels: Vec<Level<C>> = Vec::new();
    let mut cells: Vec<(i64, [f32; C])> = entries.iter().map(|e| (e.id, e.bounds)).collect();
    loop {
        let n = cells.len();
        let nodes = n.div_ceil(capacity);
        let starts: Vec<usize> = (0..=nodes).map(|j| j * n / nodes).collect();
        if levels.is_empty() {
            // A query returns a leaf's entries in cell order: ascending ids let the
            // caller's lookups by id walk its table forward.
            for w in starts.windows(2) {
                cells[w[0]..w[1]].sort_unstable_by_key(|c| c.0);
            }
        }
        let parents: Vec<(i64, [f32; C])> = starts
            .windows(2)
            .map(|w| {
                let mut hull = cells[w[0]].1;
                for (_, b) in &cells[w[0] + 1..w[1]] {
                    for d in 0..C / 2 {
                        hull[2 * d] = hull[2 * d].min(b[2 * d]);
                        hull[2 * d + 1] = hull[2 * d + 1].max(b[2 * d + 1]);
                    }
                }
                (0, hull)
            })
            .collect();
        levels.push(Level { cells, starts });
        if nodes == 1 {
            break;
        }
        cells = parents;
    }
    let depth = levels.len() - 1;
    if depth > 40 {
        return Err(corrupt(format!("depth {depth} is past the module's limit")));
    }

    // Node numbers top-down, the root first, each level in packing order.
    let mut next_node = 1i64;
    let mut node_numbers: Vec<Vec<i64>> = Vec::with_capacity(levels.len());
    for level in levels.iter().rev() {
        let count = level.starts.len() - 1;
        node_numbers.push((next_node..next_node + count as i64).collect());
        next_node += count as i64;
    }
    node_numbers.reverse(); // node_numbers[h]: the nodes of levels[h]
    for h in 1..levels.len() {
        for (cell, &child) in levels[h].cells.iter_mut().zip(&node_numbers[h - 1]) {
            cell.0 = child;
        }
    }

    let mut write_node = conn
        .prepare(&format!("INSERT OR REPLACE INTO {} (nodeno, data) VALUES (?1, ?2)", shadow("_node")))
        .at(path)?;
    let mut blob = vec![0u8; node_size];
    let mut leaf_of: Vec<(i64, i64)> = Vec::with_capacity(entries.len());
    let mut parent_of: Vec<(i64, i64)> = Vec::new();
    for h in (0..levels.len()).rev() {
        let level = &levels[h];
        for (j, w) in level.starts.windows(2).enumerate() {
            let node = node_numbers[h][j];
            blob.fill(0);
            if node == 1 {
                blob[0..2].copy_from_slice(&(depth as u16).to_be_bytes());
            }
            blob[2..4].copy_from_slice(&((w[1] - w[0]) as u16).to_be_bytes());
            for (k, (id, b)) in level.cells[w[0]..w[1]].iter().enumerate() {
                let at = 4 + k * cell_bytes;
                blob[at..at + 8].copy_from_slice(&id.to_be_bytes());
                for (c, v) in b.iter().enumerate() {
                    blob[at + 8 + 4 * c..at + 12 + 4 * c].copy_from_slice(&v.to_bits().to_be_bytes());
                }
                if h == 0 { &mut leaf_of } else { &mut parent_of }.push((*id, node));
            }
            write_node.execute((node, &blob)).at(path)?;
        }
    }
    leaf_of.sort_unstable();
    insert_pairs(conn, path, &format!("{} (rowid, nodeno)", shadow("_rowid")), &leaf_of)?;
    parent_of.sort_unstable();
    insert_pairs(conn, path, &format!("{} (nodeno, parentnode)", shadow("_parent")), &parent_of)
}

/// `INSERT INTO {into} VALUES` the integer pairs, many rows per statement.
fn insert_pairs(conn: &Connection, path: &Path, into: &str, pairs: &[(i64, i64)]) -> Result<(), StoreError> {
    const ROWS: usize = 128;
    let sql = |rows: usize| format!("INSERT INTO {into} VALUES {}", vec!["(?, ?)"; rows].join(", "));
    let chunks = pairs.chunks_exact(ROWS);
    let rest = chunks.remainder();
    let run = |stmt: &mut rusqlite::Statement<'_>, rows: &[(i64, i64)]| -> rusqlite::Result<()> {
        for (i, (a, b)) in rows.iter().enumerate() {
            stmt.raw_bind_parameter(2 * i + 1, a)?;
            stmt.raw_bind_parameter(2 * i + 2, b)?;
        }
        stmt.raw_execute().map(|_| ())
    };
    if pairs.len() >= ROWS {
        let mut stmt = conn.prepare(&sql(ROWS)).at(path)?;
        for chunk in chunks {
            run(&mut stmt, chunk).at(path)?;
        }
    }
    if !rest.is_empty() {
        run(&mut conn.prepare(&sql(rest.len())).at(path)?, rest).at(path)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_matches_the_module() {
        let conn = Connection::open_in_memory().unwrap();
        conn.execute_batch("CREATE VIRTUAL TABLE r USING rtree(id, lo, hi)").unwrap();
        let values = [
            0.0,
            -0.0,
            1.0 / 3.0,
            -1.0 / 3.0,
            7.123_456_789_012_3,
            -179.999_999_9,
            180.000_000_01,
            46.5 + 1e-9,
            f64::from(f32::MAX),
            1e-40,
            -1e-40,
            123_456_789.123,
        ];
        for (i, &v) in values.iter().enumerate() {
            conn.execute("INSERT INTO r VALUES (?1, ?2, ?3)", (i as i64, v, v)).unwrap();
            let (lo, hi): (f64, f64) = conn
                .query_row("SELECT lo, hi FROM r WHERE id = ?1", [i as i64], |r| Ok((r.get(0)?, r.get(1)?)))
                .unwrap();
            assert_eq!((lo as f32).to_bits(), round_down(v).to_bits(), "{v}");
            assert_eq!((hi as f32).to_bits(), round_up(v).to_bits(), "{v}");
            // Outward, except where the module's rounding is not (float32 subnormals).
            if v == 0.0 || v.abs() > 1e-30 {
                assert!(f64::from(round_down(v)) <= v && f64::from(round_up(v)) >= v, "{v}");
            }
        }
    }

    #[test]
    fn hilbert_key_visits_each_cell_once() {
        let mut keys: Vec<u64> = (0..64u32)
            .flat_map(|i| (0..64u32).map(move |j| (i, j)))
            .map(|(i, j)| hilbert_key(f64::from(i) / 63.0, f64::from(j) / 63.0))
            .collect();
        keys.sort_unstable();
        keys.dedup();
        assert_eq!(keys.len(), 64 * 64);
        assert_eq!(hilbert_key(0.0, 0.0), 0);
        assert_eq!(hilbert_key(1.0, 0.0), (1u64 << 32) - 1);
    }

    /// Boxes in three dimensions with clusters, duplicates and a huge one.
    fn boxes(n: usize) -> Vec<(i64, [f64; 6])> {
        let mut state = 7u64;
        let mut unit = move || {
            state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|i| {
                let (x, y, z) = (7.0 + unit() * 0.1, 46.0 + unit() * 0.1, (i % 5) as f64);
                let (w, h) = (unit() * 1e-3, unit() * 1e-3);
                let b = if i % 997 == 3 {
                    [-180.0, 180.0, y, y + h, z - 0.5, z + 0.5]
                } else if i % 101 == 5 {
                    [x, x, y, y, z - 0.5, z + 0.5]
                } else {
                    [x - w, x + w, y - h, y + h, z - 0.5, z + 0.5]
                };
                (1 + i as i64 * 3, b)
            })
            .collect()
    }

    fn load(conn: &Connection, table: &str, boxes: &[(i64, [f64; 6])]) {
        let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
        for (_, b) in boxes {
            for d in 0..2 {
                let c = (b[2 * d] + b[2 * d + 1]) / 2.0;
                lo[d] = lo[d].min(c);
                hi[d] = hi[d].max(c);
            }
        }
        let mut entries: Vec<Entry<6>> = boxes
            .iter()
            .map(|(id, b)| {
                let x = ((b[0] + b[1]) / 2.0 - lo[0]) / (hi[0] - lo[0]).max(f64::MIN_POSITIVE);
                let y = ((b[2] + b[3]) / 2.0 - lo[1]) / (hi[1] - lo[1]).max(f64::MIN_POSITIVE);
                Entry::new(*id, ((b[4] + 0.5) as u64) << 32 | hilbert_key(x, y), *b).unwrap()
            })
            .collect();
        bulk_load(conn, Path::new("test"), table, &mut entries).unwrap();
    }

    fn rows(conn: &Connection, sql: &str) -> Vec<Vec<f64>> {
        let mut stmt = conn.prepare(sql).unwrap();
        let ncol = stmt.column_count();
        stmt.query_map([], |r| (0..ncol).map(|i| r.get::<_, f64>(i)).collect::<rusqlite::Result<Vec<f64>>>())
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap()
    }

    /// The packed tree holds exactly what SQLite's own inserts store, passes
    /// rtreecheck, answers queries alike, and stays writable through the module.
    #[test]
    fn packed_tree_equals_inserted_tree() {
        for n in [0usize, 1, 50, 51, 52, 2601, 2602, 20_000] {
            let conn = Connection::open_in_memory().unwrap();
            conn.execute_batch(
                "CREATE VIRTUAL TABLE packed USING rtree(id, x0, x1, y0, y1, z0, z1);
                 CREATE VIRTUAL TABLE inserted USING rtree(id, x0, x1, y0, y1, z0, z1);",
            )
            .unwrap();
            let boxes = boxes(n);
            load(&conn, "packed", &boxes);
            {
                let mut insert =
                    conn.prepare("INSERT INTO inserted VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)").unwrap();
                for (id, b) in &boxes {
                    insert.execute(rusqlite::params![id, b[0], b[1], b[2], b[3], b[4], b[5]]).unwrap();
                }
            }
            let check: String = conn.query_row("SELECT rtreecheck('packed')", [], |r| r.get(0)).unwrap();
            assert_eq!(check, "ok", "n = {n}");
            let all = |t: &str| rows(&conn, &format!("SELECT * FROM {t} ORDER BY id"));
            assert_eq!(all("packed"), all("inserted"), "n = {n}");
            let nodes: i64 = conn.query_row("SELECT count(*) FROM packed_node", [], |r| r.get(0)).unwrap();
            assert!(nodes as usize <= 1 + n.div_ceil(50) + n.div_ceil(50 * 50), "n = {n}: {nodes} nodes");
            for q in [
                "x1 >= 7.05 AND x0 <= 7.06 AND y1 >= 46.02 AND y0 <= 46.03",
                "z1 >= 2 AND z0 <= 2",
                "x0 > 7.09",
            ] {
                let ids = |t: &str| rows(&conn, &format!("SELECT id FROM {t} WHERE {q} ORDER BY id"));
                assert_eq!(ids("packed"), ids("inserted"), "n = {n}: {q}");
            }
            // Later writes through the module keep it consistent.
            conn.execute_batch(
                "INSERT INTO packed VALUES (1000000, 7.0, 7.2, 46.0, 46.2, 0, 9);
                 DELETE FROM packed WHERE id % 7 = 1;
                 INSERT INTO packed SELECT id + 2000000, x0, x1, y0, y1, z0, z1 FROM inserted WHERE id % 5 = 0;",
            )
            .unwrap();
            let check: String = conn.query_row("SELECT rtreecheck('packed')", [], |r| r.get(0)).unwrap();
            assert_eq!(check, "ok", "n = {n} after writes");
        }
    }

    #[test]
    fn refuses_a_filled_tree_and_inverted_boxes() {
        let conn = Connection::open_in_memory().unwrap();
        conn.execute_batch("CREATE VIRTUAL TABLE r USING rtree(id, x0, x1); INSERT INTO r VALUES (1, 0, 1);")
            .unwrap();
        let mut entries = [Entry::new(2, 0, [0.0, 1.0]).unwrap()];
        let err = bulk_load(&conn, Path::new("t.gpkg"), "r", &mut entries).unwrap_err();
        assert!(err.to_string().contains("not a fresh"), "{err}");
        conn.execute_batch("CREATE VIRTUAL TABLE r2 USING rtree(id, x0, x1)").unwrap();
        let mut entries = [Entry::new(2, 0, [0.0, 1.0, 0.0, 1.0]).unwrap()];
        let err = bulk_load(&conn, Path::new("t.gpkg"), "r2", &mut entries).unwrap_err();
        assert!(err.to_string().contains("not a fresh R*Tree of 2 dimensions (3 columns"), "{err}");
        assert_eq!(Entry::<4>::new(1, 0, [0.0, 1.0, 2.0, 1.0]).unwrap_err(), 1);
        assert_eq!(Entry::<2>::new(1, 0, [f64::NAN, 1.0]).unwrap_err(), 0);
    }
}

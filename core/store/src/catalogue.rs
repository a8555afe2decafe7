//! The whole database in memory, for the landmark server's hot path.
//!
//! A [`Catalogue`] holds every template already in the binary wire encoding
//! ([`trn_landmark::wire`]), back to back, and one in-memory R*-tree of exact
//! (f64) footprint boxes per level. A bounding-box query is then an index walk,
//! a sort and a copy of the chosen records: no SQL, no per-row decoding, and it
//! answers exactly what [`LandmarkDb::query_bbox`] answers, in the same order.
//! SQLite costs a few microseconds per row read (its virtual machine, 24 column
//! reads, the R*Tree module's node reads), which for a navigator's footprint of
//! ~1000 templates is milliseconds; the catalogue does it in a fraction of one.
//!
//! The database file is immutable, so what is loaded stays true; a new version
//! is a new file and a new catalogue.

use std::collections::BTreeMap;

use rstar::primitives::{GeomWithData, Rectangle};
use rstar::{RTree, AABB};
use trn_landmark::{wire, GeoBox, Template};

use crate::error::{SqlContext, StoreError, StoreErrorKind};
use crate::reader::{best_first, Rank};
use crate::{BboxQuery, LandmarkDb, LevelInfo};

/// Bytes of memory per template besides its record: the entry, its share of
/// the R*-tree and the allocator's (231 measured on the 128 681-template
/// benchmark database, from the server's resident memory).
const INDEX_BYTES_PER_TEMPLATE: u64 = 240;

/// A footprint box in the index (a half, for one crossing the antimeridian),
/// pointing at its entry.
type Indexed = GeomWithData<Rectangle<[f64; 2]>, u32>;

#[derive(Clone, Debug)]
struct Entry {
    rank: Rank,
    footprint: GeoBox,
    /// The record's bytes in `records`.
    start: usize,
    len: usize,
}

/// Every template of one database version in memory, encoded, with a spatial index.
pub struct Catalogue {
    /// The database file it was read from (for messages).
    path: std::path::PathBuf,
    levels: Vec<LevelInfo>,
    by_level: BTreeMap<u8, RTree<Indexed>>,
    entries: Vec<Entry>,
    records: Vec<u8>,
}

impl std::fmt::Debug for Catalogue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Catalogue")
            .field("templates", &self.entries.len())
            .field("memory_bytes", &self.memory_bytes())
            .finish()
    }
}

impl LandmarkDb {
    /// Bytes a [`Catalogue`] of this database would take (records and index),
    /// from the blob lengths alone (a quick scan, no blob is read).
    pub fn catalogue_bytes(&self) -> Result<u64, StoreError> {
        let (count, blobs): (i64, f64) = self
            .conn()
            .query_row(
                "SELECT count(*), total(length(pixels) + length(height_grid_heights_m)) FROM templates",
                [],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
            .at(self.path())?;
        Ok(count as u64 * (wire::MIN_RECORD_LEN as u64 + INDEX_BYTES_PER_TEMPLATE) + blobs as u64)
    }

    /// Reads every template into a [`Catalogue`].
    pub fn load_catalogue(&self) -> Result<Catalogue, StoreError> {
        let levels = self.levels()?;
        let count: u64 = levels.iter().map(|l| l.count).sum();
        let mut entries = Vec::with_capacity(count as usize);
        let mut records = Vec::new();
        let mut boxes: BTreeMap<u8, Vec<Indexed>> = BTreeMap::new();
        self.for_each_template(|t| {
            let corrupt = |why: &str| {
                StoreError::new(self.path(), StoreErrorKind::Corrupt(why.into())).with_template_id(t.id)
            };
            let fp = t.footprint;
            let finite = [fp.min_lon_deg, fp.min_lat_deg, fp.max_lon_deg, fp.max_lat_deg]
                .iter()
                .all(|v| v.is_finite());
            if !finite || fp.min_lat_deg > fp.max_lat_deg {
                return Err(corrupt("footprint is not a box (NaN, infinite or reversed latitudes)"));
            }
            let index = u32::try_from(entries.len()).map_err(|_| corrupt("more than 2^32 templates"))?;
            if records.capacity() == 0 {
                // Templates of a database share their size: one allocation.
                records.reserve(count as usize * wire::encoded_len(&t));
            }
            let start = records.len();
            wire::encode_record(&t, &mut records);
            let tree = boxes.entry(t.level).or_default();
            for half in fp.split_antimeridian() {
                let rect = Rectangle::from_corners(
                    [half.min_lon_deg, half.min_lat_deg],
                    [half.max_lon_deg, half.max_lat_deg],
                );
                tree.push(GeomWithData::new(rect, index));
            }
            entries.push(Entry { rank: Rank::of(&t), footprint: fp, start, len: records.len() - start });
            Ok(())
        })?;
        records.shrink_to_fit();
        let by_level = boxes.into_iter().map(|(l, b)| (l, RTree::bulk_load(b))).collect();
        Ok(Catalogue { path: self.path().to_owned(), levels, by_level, entries, records })
    }
}

impl Catalogue {
    /// The levels present, finest first (as [`LandmarkDb::levels`]).
    pub fn levels(&self) -> &[LevelInfo] {
        &self.levels
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Bytes held: the records plus an estimate of the index.
    pub fn memory_bytes(&self) -> u64 {
        self.records.len() as u64 + self.entries.len() as u64 * INDEX_BYTES_PER_TEMPLATE
    }

    /// The encoded records of the templates matching `query`, best first: the
    /// templates of [`LandmarkDb::query_bbox`], in its order.
    pub fn query(&self, query: &BboxQuery) -> Vec<&[u8]> {
        let (lo, hi) = query.levels.as_ref().map_or((0, u8::MAX), |r| (*r.start(), *r.end()));
        if lo > hi || query.limit == Some(0) {
            return Vec::new();
        }
        let mut found = Vec::new();
        for part in query.bbox.split_antimeridian() {
            let aabb = AABB::from_corners(
                [part.min_lon_deg, part.min_lat_deg],
                [part.max_lon_deg, part.max_lat_deg],
            );
            for tree in self.by_level.range(lo..=hi).map(|(_, t)| t) {
                for hit in tree.locate_in_envelope_intersecting(&aabb) {
                    let e = &self.entries[hit.data as usize];
                    if query.lighting.is_some_and(|k| self.records[e.start + wire::LIGHTING_OFFSET] != k) {
                        continue;
                    }
                    // The index is exact already; the recheck keeps one definition.
                    if query.bbox.intersects(&e.footprint) {
                        found.push((e.rank, hit.data));
                    }
                }
            }
        }
        best_first(&mut found, query.limit);
        found
            .into_iter()
            .map(|(_, i)| {
                let e = &self.entries[i as usize];
                &self.records[e.start..e.start + e.len]
            })
            .collect()
    }

    /// The templates matching `query`, decoded (as [`LandmarkDb::query_bbox`]).
    pub fn query_templates(&self, query: &BboxQuery) -> Result<Vec<Template>, StoreError> {
        self.query(query)
            .into_iter()
            .map(|r| {
                wire::decode_record(r)
                    .map_err(|e| StoreError::new(&self.path, StoreErrorKind::Corrupt(e.to_string())))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::DbWriter;
    use trn_geodesy::Geodetic;
    use trn_landmark::{HeightGrid, TemplateQuality, TerrainPatch};

    fn lcg(s: &mut u64) -> f64 {
        *s = s.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        (*s >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Templates at three levels, some near and across the antimeridian, with
    /// ties in the ranking keys.
    fn templates(n: usize, seed: u64) -> Vec<Template> {
        let mut s = seed;
        (0..n)
            .map(|i| {
                let level = (i % 3) as u8;
                let half = 0.001 * f64::from(1u32 << level);
                let lat = -10.0 + 20.0 * lcg(&mut s);
                let lon =
                    if i % 5 == 0 { 179.995 + 0.01 * lcg(&mut s) } else { -180.0 + 360.0 * lcg(&mut s) };
                let wrap = |x: f64| if x > 180.0 { x - 360.0 } else { x };
                let side = 4 + (i % 3) as u32;
                Template {
                    id: 0,
                    level,
                    gsd_m: 1.0 + level as f64,
                    width_px: side,
                    height_px: side,
                    center: Geodetic::new(lat, wrap(lon), 100.0),
                    footprint: GeoBox::new(wrap(lon - half), lat - half, wrap(lon + half), lat + half),
                    terrain: TerrainPatch {
                        plane_normal_enu: [0.0, 0.0, 1.0],
                        plane_residual_rms_m: 0.5,
                        height_grid: HeightGrid { n: 2, spacing_m: 1.0, heights_m: vec![i as f32; 4] },
                    },
                    quality: TemplateQuality {
                        shi_tomasi: (lcg(&mut s) * 4.0).floor() as f32,
                        contrast_std: 1.0,
                        second_peak_ncc: (lcg(&mut s) * 3.0).floor() as f32 / 4.0,
                        shading_share: 0.25,
                    },
                    source: 0,
                    lighting: (i % 2) as u8,
                    pixels: (0..side * side).map(|k| (k as usize + i) as u8).collect(),
                }
            })
            .collect()
    }

    #[test]
    fn answers_what_sqlite_answers_in_the_same_order() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.gpkg");
        let mut ts = templates(3000, 5);
        let mut w = DbWriter::create(&path).unwrap();
        w.insert_batch(&mut ts).unwrap();
        w.finish().unwrap();
        let db = LandmarkDb::open(&path).unwrap();
        let cat = db.load_catalogue().unwrap();
        assert_eq!(cat.len(), 3000);
        assert_eq!(cat.levels(), db.levels().unwrap().as_slice());
        let estimate = db.catalogue_bytes().unwrap();
        assert!(estimate >= cat.memory_bytes(), "estimate {estimate} < {}", cat.memory_bytes());
        let mut s = 99u64;
        let mut nonempty = 0;
        for k in 0..400 {
            let (w, h) = (0.02 + 3.0 * lcg(&mut s) * lcg(&mut s), 0.02 + 2.0 * lcg(&mut s));
            let lat = -12.0 + 24.0 * lcg(&mut s);
            // Every fourth box around the antimeridian, some crossing it.
            let lon = if k % 4 == 0 { 179.0 + 2.0 * lcg(&mut s) } else { -180.0 + 360.0 * lcg(&mut s) };
            let wrap = |x: f64| {
                if x > 180.0 {
                    x - 360.0
                } else if x < -180.0 {
                    x + 360.0
                } else {
                    x
                }
            };
            let bbox = GeoBox::new(wrap(lon - w), lat - h, wrap(lon + w), lat + h);
            let mut q = BboxQuery::new(bbox);
            if k % 3 == 1 {
                q = q.with_levels(1..=1);
            } else if k % 3 == 2 {
                q = q.with_levels(1..=2);
            }
            if k % 7 == 0 {
                q = q.with_limit(5);
            }
            if k % 5 == 0 {
                q = q.with_lighting((k / 5 % 2) as u8);
            }
            let want = db.query_bbox(&q).unwrap();
            let got = cat.query_templates(&q).unwrap();
            assert_eq!(got, want, "query {k}: {q:?}");
            nonempty += usize::from(!want.is_empty());
        }
        assert!(nonempty > 100, "only {nonempty} queries found templates");
        // The whole globe, level by level, and nothing for an empty level range.
        let all = BboxQuery::new(GeoBox::new(-180.0, -90.0, 180.0, 90.0));
        assert_eq!(cat.query(&all).len(), 3000);
        assert!(cat.query(&all.clone().with_levels(9..=9)).is_empty());
        assert!(cat.query(&all.with_limit(0)).is_empty());
    }
}

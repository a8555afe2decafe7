//! The compact binary encoding of template lists (`application/vnd.trn.templates`),
//! as the landmark server sends them and the navigator's HTTP source reads them.
//!
//! Lossless: every field of a [`Template`] is written with its own width
//! (f64 as f64, f32 as f32), so a decoded template equals the stored one bit for bit.
//! All numbers are little-endian, nothing is aligned or padded.
//!
//! ```text
//! header   magic  b"TRNT"             4 bytes
//!          version u32 = 1
//!          flags   u32                bit 0: the list was truncated by a limit
//!          count   u32                number of records that follow
//! record   id i64, level u8, lighting u8, width_px u32, height_px u32, source u32, gsd_m f64,
//!          lat_deg f64, lon_deg f64, h_m f64 (WGS84 ellipsoidal),
//!          footprint min_lon_deg, min_lat_deg, max_lon_deg, max_lat_deg (4 x f64),
//!          plane_normal_enu (3 x f64), plane_residual_rms_m f64,
//!          height_grid n u32, spacing_m f64, heights_m (n*n x f32, row 0 north),
//!          shi_tomasi f32, contrast_std f32, second_peak_ncc f32, shading_share f32,
//!          pixels (width_px*height_px x u8, row-major, row 0 north)
//! ```

use std::fmt;

use trn_geodesy::Geodetic;

use crate::{GeoBox, HeightGrid, Template, TemplateQuality, TerrainPatch};

/// Media type of the encoding (HTTP `Accept` / `Content-Type`).
pub const MEDIA_TYPE: &str = "application/vnd.trn.templates";
pub const MAGIC: [u8; 4] = *b"TRNT";
pub const VERSION: u32 = 2;
/// Largest template side and height grid side a decoder accepts: anything larger is
/// a corrupt stream, not a template, and must not make it allocate gigabytes.
pub const MAX_SIDE: u32 = 4096;
pub const MAX_GRID_N: u32 = 1024;

/// A template list as sent over the wire.
#[derive(Clone, Debug, PartialEq)]
pub struct TemplateList {
    pub templates: Vec<Template>,
    /// Whether a limit cut the list short.
    pub truncated: bool,
}

/// Why a byte stream is not a template list; says at which byte.
#[derive(Clone, Debug, PartialEq)]
pub struct WireError(pub String);

impl fmt::Display for WireError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "bad {MEDIA_TYPE} body: {}", self.0)
    }
}

impl std::error::Error for WireError {}

/// Where a record's `lighting` byte is (after `id` and `level`).
pub const LIGHTING_OFFSET: usize = 9;

/// Bytes of a record without height grid and pixels.
pub const MIN_RECORD_LEN: usize = 8 + 2 + 4 * 3 + 8 * 12 + 4 + 8 + 4 * 4;

/// Bytes one template takes.
pub fn encoded_len(t: &Template) -> usize {
    MIN_RECORD_LEN + 4 * t.terrain.height_grid.heights_m.len() + t.pixels.len()
}

/// Bytes of the header.
pub const HEADER_LEN: usize = 16;

/// Encodes `templates` with the header.
pub fn encode<'a>(templates: impl IntoIterator<Item = &'a Template>, truncated: bool) -> Vec<u8> {
    let list: Vec<&Template> = templates.into_iter().collect();
    let mut out = Vec::with_capacity(HEADER_LEN + list.iter().map(|t| encoded_len(t)).sum::<usize>());
    write_header(&mut out, list.len() as u32, truncated);
    for t in list {
        encode_record(t, &mut out);
    }
    out
}

/// Appends the header of a list of `count` records (which the caller then
/// appends, e.g. records kept from [`encode_record`]).
pub fn write_header(out: &mut Vec<u8>, count: u32, truncated: bool) {
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&u32::from(truncated).to_le_bytes());
    out.extend_from_slice(&count.to_le_bytes());
}

/// Appends one template's record ([`encoded_len`] bytes).
pub fn encode_record(t: &Template, out: &mut Vec<u8>) {
    out.extend_from_slice(&t.id.to_le_bytes());
    out.push(t.level);
    out.push(t.lighting);
    for v in [t.width_px, t.height_px, t.source] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    let f = &t.footprint;
    let tr = &t.terrain;
    for v in [
        t.gsd_m,
        t.center.lat_deg,
        t.center.lon_deg,
        t.center.h_m,
        f.min_lon_deg,
        f.min_lat_deg,
        f.max_lon_deg,
        f.max_lat_deg,
        tr.plane_normal_enu[0],
        tr.plane_normal_enu[1],
        tr.plane_normal_enu[2],
        tr.plane_residual_rms_m,
    ] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&tr.height_grid.n.to_le_bytes());
    out.extend_from_slice(&tr.height_grid.spacing_m.to_le_bytes());
    for h in &tr.height_grid.heights_m {
        out.extend_from_slice(&h.to_le_bytes());
    }
    let q = &t.quality;
    for v in [q.shi_tomasi, q.contrast_std, q.second_peak_ncc, q.shading_share] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&t.pixels);
}

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], WireError> {
        if self.buf.len() - self.pos < n {
            return Err(WireError(format!(
                "ends at byte {} inside {what} ({n} bytes needed, {} left)",
                self.buf.len(),
                self.buf.len() - self.pos
            )));
        }
        let s = &self.buf[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N], WireError> {
        Ok(self.take(N, what)?.try_into().expect("length checked"))
    }

    fn u32(&mut self, what: &str) -> Result<u32, WireError> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    fn f64(&mut self, what: &str) -> Result<f64, WireError> {
        Ok(f64::from_le_bytes(self.array(what)?))
    }

    fn f32(&mut self, what: &str) -> Result<f32, WireError> {
        Ok(f32::from_le_bytes(self.array(what)?))
    }
}

/// Decodes a whole body; trailing bytes are an error.
pub fn decode(bytes: &[u8]) -> Result<TemplateList, WireError> {
    let mut r = Reader { buf: bytes, pos: 0 };
    let magic = r.array::<4>("the magic")?;
    if magic != MAGIC {
        return Err(WireError(format!("magic {magic:?}, expected {MAGIC:?} (\"TRNT\")")));
    }
    let version = r.u32("the version")?;
    if version != VERSION {
        return Err(WireError(format!("version {version}, this trn reads version {VERSION}")));
    }
    let flags = r.u32("the flags")?;
    let count = r.u32("the count")? as usize;
    // Each record takes at least MIN_RECORD_LEN bytes: a count beyond that is a lie.
    if count > bytes.len() / MIN_RECORD_LEN {
        return Err(WireError(format!("count {count} cannot fit in {} bytes", bytes.len())));
    }
    let mut templates = Vec::with_capacity(count);
    for i in 0..count {
        templates.push(decode_one(&mut r).map_err(|e| WireError(format!("record {i}: {}", e.0)))?);
    }
    if r.pos != bytes.len() {
        return Err(WireError(format!("{} bytes after the last record", bytes.len() - r.pos)));
    }
    Ok(TemplateList { templates, truncated: flags & 1 != 0 })
}

/// Decodes one record (as [`encode_record`] wrote it); trailing bytes are an error.
pub fn decode_record(bytes: &[u8]) -> Result<Template, WireError> {
    let mut r = Reader { buf: bytes, pos: 0 };
    let t = decode_one(&mut r)?;
    if r.pos != bytes.len() {
        return Err(WireError(format!("{} bytes after the record", bytes.len() - r.pos)));
    }
    Ok(t)
}

fn decode_one(r: &mut Reader) -> Result<Template, WireError> {
    let id = i64::from_le_bytes(r.array("id")?);
    let level = r.take(1, "level")?[0];
    let lighting = r.take(1, "lighting")?[0];
    let width_px = r.u32("width_px")?;
    let height_px = r.u32("height_px")?;
    if width_px > MAX_SIDE || height_px > MAX_SIDE {
        return Err(WireError(format!("template {id}: {width_px}x{height_px} px exceeds {MAX_SIDE}")));
    }
    let source = r.u32("source")?;
    let gsd_m = r.f64("gsd_m")?;
    let center = Geodetic::new(r.f64("lat_deg")?, r.f64("lon_deg")?, r.f64("h_m")?);
    let footprint =
        GeoBox::new(r.f64("footprint")?, r.f64("footprint")?, r.f64("footprint")?, r.f64("footprint")?);
    let plane_normal_enu = [r.f64("plane_normal")?, r.f64("plane_normal")?, r.f64("plane_normal")?];
    let plane_residual_rms_m = r.f64("plane_residual_rms_m")?;
    let n = r.u32("height_grid n")?;
    if n > MAX_GRID_N {
        return Err(WireError(format!("template {id}: height grid {n}x{n} exceeds {MAX_GRID_N}")));
    }
    let spacing_m = r.f64("height_grid spacing_m")?;
    let heights = r.take(4 * (n as usize) * (n as usize), "height_grid heights")?;
    let heights_m = heights.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4"))).collect();
    let quality = TemplateQuality {
        shi_tomasi: r.f32("shi_tomasi")?,
        contrast_std: r.f32("contrast_std")?,
        second_peak_ncc: r.f32("second_peak_ncc")?,
        shading_share: r.f32("shading_share")?,
    };
    let pixels = r.take(width_px as usize * height_px as usize, "pixels")?.to_vec();
    Ok(Template {
        id,
        level,
        gsd_m,
        width_px,
        height_px,
        center,
        footprint,
        terrain: TerrainPatch {
            plane_normal_enu,
            plane_residual_rms_m,
            height_grid: HeightGrid { n, spacing_m, heights_m },
        },
        quality,
        source,
        lighting,
        pixels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn template(id: i64, side: u32, n: u32) -> Template {
        Template {
            id,
            level: 3,
            gsd_m: 8.125,
            width_px: side,
            height_px: side + 1,
            center: Geodetic::new(40.123456789012345, -105.98765432101234, 1523.4567890123),
            footprint: GeoBox::new(179.9, -1e-300, -179.9, 1.0 / 3.0),
            terrain: TerrainPatch {
                plane_normal_enu: [0.1, -0.2, 0.974679434480896],
                plane_residual_rms_m: 0.75,
                height_grid: HeightGrid {
                    n,
                    spacing_m: 3.5,
                    heights_m: (0..n * n).map(|i| i as f32 * 0.37 - 2.0).collect(),
                },
            },
            quality: TemplateQuality {
                shi_tomasi: 12.5,
                contrast_std: 30.25,
                second_peak_ncc: 0.61,
                shading_share: 0.375,
            },
            source: 2,
            lighting: 3,
            pixels: (0..side * (side + 1)).map(|i| (i * 7 % 256) as u8).collect(),
        }
    }

    #[test]
    fn round_trips_bit_for_bit() {
        let ts = vec![template(1, 32, 9), template(i64::MAX, 1, 0), template(-5, 0, 1)];
        for truncated in [false, true] {
            let bytes = encode(&ts, truncated);
            assert_eq!(bytes.len(), 16 + ts.iter().map(encoded_len).sum::<usize>());
            let back = decode(&bytes).unwrap();
            assert_eq!(back.truncated, truncated);
            assert_eq!(back.templates, ts);
        }
        assert_eq!(decode(&encode(&[], false)).unwrap().templates, vec![]);
    }

    #[test]
    fn records_written_apart_make_the_same_list() {
        let ts = vec![template(7, 8, 3), template(-2, 3, 1)];
        let mut records = Vec::new();
        for t in &ts {
            let start = records.len();
            encode_record(t, &mut records);
            assert_eq!(records.len() - start, encoded_len(t));
            assert_eq!(decode_record(&records[start..]).unwrap(), *t);
        }
        let mut out = Vec::new();
        write_header(&mut out, 2, true);
        assert_eq!(out.len(), HEADER_LEN);
        out.extend_from_slice(&records);
        assert_eq!(out, encode(&ts, true));
        let mut extra = records[..encoded_len(&ts[0])].to_vec();
        extra.push(1);
        assert!(decode_record(&extra).unwrap_err().0.contains("after the record"));
    }

    #[test]
    fn every_truncation_and_corruption_is_an_error() {
        let bytes = encode(&[template(1, 4, 3), template(2, 5, 2)], false);
        for len in 0..bytes.len() {
            assert!(decode(&bytes[..len]).is_err(), "a prefix of {len} bytes decoded");
        }
        let mut extra = bytes.clone();
        extra.push(0);
        assert!(decode(&extra).unwrap_err().0.contains("after the last record"));
        let mut bad = bytes.clone();
        bad[0] = b'X';
        assert!(decode(&bad).unwrap_err().0.contains("magic"));
        let mut huge = bytes.clone();
        huge[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode(&huge).unwrap_err().0.contains("count"));
        // A width beyond MAX_SIDE is refused before any allocation.
        let mut wide = bytes;
        wide[16 + 9..16 + 13].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode(&wide).unwrap_err().0.contains("exceeds"));
    }
}

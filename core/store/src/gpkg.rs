//! GeoPackage geometry blobs for template footprints.

use trn_landmark::GeoBox;

/// EPSG code of the footprint geometries (WGS 84 longitude/latitude).
pub const FOOTPRINT_SRS_ID: i32 = 4326;

const HEADER_LEN: usize = 8;
const ENVELOPE_LEN: usize = 32;
/// Byte order + type + ring count + point count + 5 (x, y) points.
const WKB_POLYGON_LEN: usize = 1 + 4 + 4 + 4 + 5 * 16;
/// Little-endian, envelope [minx, maxx, miny, maxy], not empty, standard geometry.
const FLAGS: u8 = 0b0000_0011;
const WKB_POLYGON: u32 = 3;

/// The polygon x range of a footprint: a footprint crossing the antimeridian is drawn
/// unwrapped, past +180, so that it stays one small polygon.
pub fn footprint_x_range(footprint: &GeoBox) -> (f64, f64) {
    if footprint.crosses_antimeridian() {
        (footprint.min_lon_deg, footprint.max_lon_deg + 360.0)
    } else {
        (footprint.min_lon_deg, footprint.max_lon_deg)
    }
}

/// Length of a footprint geometry blob.
pub(crate) const FOOTPRINT_BLOB_LEN: usize = HEADER_LEN + ENVELOPE_LEN + WKB_POLYGON_LEN;

/// GeoPackage geometry blob (OGC 12-128r17 clause 2.1.3): the 'GP' header with SRS id
/// and envelope, then the footprint box as a little-endian WKB polygon (x = longitude,
/// y = latitude), exterior ring counter-clockwise.
pub fn footprint_polygon_blob(footprint: &GeoBox) -> Vec<u8> {
    footprint_polygon(footprint).to_vec()
}

/// [`footprint_polygon_blob`] without the allocation.
pub(crate) fn footprint_polygon(footprint: &GeoBox) -> [u8; FOOTPRINT_BLOB_LEN] {
    let (min_x, max_x) = footprint_x_range(footprint);
    let (min_y, max_y) = (footprint.min_lat_deg, footprint.max_lat_deg);
    let mut b = [0u8; FOOTPRINT_BLOB_LEN];
    let mut at = 0;
    let mut put = |bytes: &[u8]| {
        b[at..at + bytes.len()].copy_from_slice(bytes);
        at += bytes.len();
    };
    put(b"GP");
    put(&[0, FLAGS]); // version 1, flags
    put(&FOOTPRINT_SRS_ID.to_le_bytes());
    for v in [min_x, max_x, min_y, max_y] {
        put(&v.to_le_bytes());
    }
    put(&[1]); // WKB little-endian
    put(&WKB_POLYGON.to_le_bytes());
    put(&1u32.to_le_bytes()); // rings
    put(&5u32.to_le_bytes()); // points, ring closed
    for (x, y) in [(min_x, min_y), (max_x, min_y), (max_x, max_y), (min_x, max_y), (min_x, min_y)] {
        put(&x.to_le_bytes());
        put(&y.to_le_bytes());
    }
    debug_assert_eq!(at, FOOTPRINT_BLOB_LEN);
    b
}

/// Reads back the envelope `(min_x, min_y, max_x, max_y)` of a blob written by
/// [`footprint_polygon_blob`]; `None` for anything else.
pub fn polygon_blob_envelope(blob: &[u8]) -> Option<(f64, f64, f64, f64)> {
    if blob.len() != FOOTPRINT_BLOB_LEN || &blob[..2] != b"GP" || blob[3] != FLAGS {
        return None;
    }
    let f =
        |i: usize| f64::from_le_bytes(blob[HEADER_LEN + 8 * i..HEADER_LEN + 8 * i + 8].try_into().unwrap());
    Some((f(0), f(2), f(1), f(3)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blob_layout() {
        let fp = GeoBox::new(7.25, 45.5, 7.75, 46.0);
        let b = footprint_polygon_blob(&fp);
        assert_eq!(b.len(), 133);
        assert_eq!(&b[..4], &[b'G', b'P', 0, 3]);
        assert_eq!(i32::from_le_bytes(b[4..8].try_into().unwrap()), 4326);
        assert_eq!(polygon_blob_envelope(&b), Some((7.25, 45.5, 7.75, 46.0)));
        // WKB: little-endian polygon, 1 ring of 5 points, first point (min_x, min_y).
        let wkb = &b[40..];
        assert_eq!(wkb[0], 1);
        assert_eq!(u32::from_le_bytes(wkb[1..5].try_into().unwrap()), 3);
        assert_eq!(u32::from_le_bytes(wkb[5..9].try_into().unwrap()), 1);
        assert_eq!(u32::from_le_bytes(wkb[9..13].try_into().unwrap()), 5);
        assert_eq!(f64::from_le_bytes(wkb[13..21].try_into().unwrap()), 7.25);
        assert_eq!(f64::from_le_bytes(wkb[21..29].try_into().unwrap()), 45.5);
    }

    #[test]
    fn antimeridian_footprint_is_unwrapped() {
        let fp = GeoBox::new(179.9, -10.0, -179.9, -9.9);
        let b = footprint_polygon_blob(&fp);
        let (min_x, _, max_x, _) = polygon_blob_envelope(&b).unwrap();
        assert_eq!(min_x, 179.9);
        assert!((max_x - 180.1).abs() < 1e-12);
    }
}

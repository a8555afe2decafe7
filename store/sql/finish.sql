-- Summaries written once by DbWriter::finish, after gpkg_rtree.sql.
-- Longitude extents use the same hull as templates_rtree: a footprint crossing the
-- antimeridian counts as the whole longitude range.

DELETE FROM trn_levels;
INSERT INTO trn_levels
SELECT level,
       min(gsd_m),
       count(*),
       min(CASE WHEN footprint_min_lon_deg <= footprint_max_lon_deg
                THEN footprint_min_lon_deg ELSE min(-180.0, footprint_max_lon_deg) END),
       min(footprint_min_lat_deg),
       max(CASE WHEN footprint_min_lon_deg <= footprint_max_lon_deg
                THEN footprint_max_lon_deg ELSE max(180.0, footprint_min_lon_deg) END),
       max(footprint_max_lat_deg)
FROM templates
GROUP BY level;

-- The layer extent for GIS clients, in geometry coordinates (see gpkg_rtree.sql).
UPDATE gpkg_contents
SET (min_x, min_y, max_x, max_y) = (
        SELECT min(footprint_min_lon_deg),
               min(footprint_min_lat_deg),
               max(CASE WHEN footprint_min_lon_deg <= footprint_max_lon_deg
                        THEN footprint_max_lon_deg ELSE footprint_max_lon_deg + 360.0 END),
               max(footprint_max_lat_deg)
        FROM templates),
    last_change = strftime('%Y-%m-%dT%H:%M:%fZ', 'now')
WHERE table_name = 'templates';

-- Spatial + level index for LandmarkDb queries, created by DbWriter::finish after the
-- bulk load (before gpkg_rtree.sql). finish fills it in one pass: it packs the tree
-- itself and writes the R*Tree's shadow tables (src/rtree.rs), with exactly the boxes
-- that the insert trigger below gives. The triggers serve later writers.
--
-- Float32 bounds rounded outward by SQLite: a coarse filter only, rechecked against the
-- footprint columns. A footprint crossing the antimeridian is entered with the hull of
-- its two halves, i.e. the whole longitude range. A template's level range is
-- [level - 0.5, level + 0.5]: the R*Tree chooses subtrees by volume growth, and flat
-- boxes (zero volume) would make that choice arbitrary and the tree useless. For
-- integer levels L1 <= L2, "max_level >= L1 AND min_level <= L2" selects exactly the
-- levels L1..L2.
CREATE VIRTUAL TABLE templates_rtree USING rtree(
    id, min_lon, max_lon, min_lat, max_lat, min_level, max_level);

-- Plain-SQL triggers keep templates_rtree in step with templates, whoever writes next.
CREATE TRIGGER templates_rtree_insert AFTER INSERT ON templates
BEGIN
    INSERT INTO templates_rtree VALUES (
        NEW.fid,
        CASE WHEN NEW.footprint_min_lon_deg <= NEW.footprint_max_lon_deg
             THEN NEW.footprint_min_lon_deg ELSE min(-180.0, NEW.footprint_max_lon_deg) END,
        CASE WHEN NEW.footprint_min_lon_deg <= NEW.footprint_max_lon_deg
             THEN NEW.footprint_max_lon_deg ELSE max(180.0, NEW.footprint_min_lon_deg) END,
        NEW.footprint_min_lat_deg, NEW.footprint_max_lat_deg,
        NEW.level - 0.5, NEW.level + 0.5);
END;

CREATE TRIGGER templates_rtree_update AFTER UPDATE OF
    fid, level, footprint_min_lon_deg, footprint_min_lat_deg, footprint_max_lon_deg,
    footprint_max_lat_deg ON templates
BEGIN
    DELETE FROM templates_rtree WHERE id = OLD.fid;
    INSERT INTO templates_rtree VALUES (
        NEW.fid,
        CASE WHEN NEW.footprint_min_lon_deg <= NEW.footprint_max_lon_deg
             THEN NEW.footprint_min_lon_deg ELSE min(-180.0, NEW.footprint_max_lon_deg) END,
        CASE WHEN NEW.footprint_min_lon_deg <= NEW.footprint_max_lon_deg
             THEN NEW.footprint_max_lon_deg ELSE max(180.0, NEW.footprint_min_lon_deg) END,
        NEW.footprint_min_lat_deg, NEW.footprint_max_lat_deg,
        NEW.level - 0.5, NEW.level + 0.5);
END;

CREATE TRIGGER templates_rtree_delete AFTER DELETE ON templates
BEGIN
    DELETE FROM templates_rtree WHERE id = OLD.fid;
END;

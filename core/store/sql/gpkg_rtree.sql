-- GeoPackage R*Tree spatial index extension (OGC 12-128r17 Annex F.3) on templates.geom,
-- created once by DbWriter::finish after the bulk load and templates_rtree.sql: the
-- triggers call the ST_* functions, which GDAL/QGIS provide but our plain SQLite
-- connection does not. finish fills the R*Tree like templates_rtree (src/rtree.rs),
-- with the envelope of the geometry blob: (footprint_min_lon_deg,
-- footprint_max_lon_deg, footprint_min_lat_deg, footprint_max_lat_deg), where a
-- footprint crossing the antimeridian is drawn with max x = footprint_max_lon_deg + 360.

CREATE VIRTUAL TABLE rtree_templates_geom USING rtree(id, minx, maxx, miny, maxy);

INSERT INTO gpkg_extensions VALUES (
    'templates', 'geom', 'gpkg_rtree_index',
    'http://www.geopackage.org/spec120/#extension_rtree', 'write-only');

CREATE TRIGGER rtree_templates_geom_insert AFTER INSERT ON templates
WHEN (NEW.geom NOT NULL AND NOT ST_IsEmpty(NEW.geom))
BEGIN
    INSERT OR REPLACE INTO rtree_templates_geom VALUES (
        NEW.fid,
        ST_MinX(NEW.geom), ST_MaxX(NEW.geom),
        ST_MinY(NEW.geom), ST_MaxY(NEW.geom));
END;

CREATE TRIGGER rtree_templates_geom_update1 AFTER UPDATE OF geom ON templates
WHEN OLD.fid = NEW.fid AND (NEW.geom NOTNULL AND NOT ST_IsEmpty(NEW.geom))
BEGIN
    INSERT OR REPLACE INTO rtree_templates_geom VALUES (
        NEW.fid,
        ST_MinX(NEW.geom), ST_MaxX(NEW.geom),
        ST_MinY(NEW.geom), ST_MaxY(NEW.geom));
END;

CREATE TRIGGER rtree_templates_geom_update2 AFTER UPDATE OF geom ON templates
WHEN OLD.fid = NEW.fid AND (NEW.geom ISNULL OR ST_IsEmpty(NEW.geom))
BEGIN
    DELETE FROM rtree_templates_geom WHERE id = OLD.fid;
END;

CREATE TRIGGER rtree_templates_geom_update3 AFTER UPDATE ON templates
WHEN OLD.fid != NEW.fid AND (NEW.geom NOTNULL AND NOT ST_IsEmpty(NEW.geom))
BEGIN
    DELETE FROM rtree_templates_geom WHERE id = OLD.fid;
    INSERT OR REPLACE INTO rtree_templates_geom VALUES (
        NEW.fid,
        ST_MinX(NEW.geom), ST_MaxX(NEW.geom),
        ST_MinY(NEW.geom), ST_MaxY(NEW.geom));
END;

CREATE TRIGGER rtree_templates_geom_update4 AFTER UPDATE ON templates
WHEN OLD.fid != NEW.fid AND (NEW.geom ISNULL OR ST_IsEmpty(NEW.geom))
BEGIN
    DELETE FROM rtree_templates_geom WHERE id IN (OLD.fid, NEW.fid);
END;

CREATE TRIGGER rtree_templates_geom_delete AFTER DELETE ON templates
WHEN OLD.geom NOT NULL
BEGIN
    DELETE FROM rtree_templates_geom WHERE id = OLD.fid;
END;

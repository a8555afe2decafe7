-- trn landmark schema on top of the GeoPackage core (gpkg_core.sql). Run once by
-- DbWriter::create. Our own schema version is the 'schema_version' row of
-- trn_metadata (user_version belongs to GeoPackage); bump SCHEMA_VERSION in lib.rs
-- with every change here.

-- Build metadata: one JSON document per key.
CREATE TABLE trn_metadata (
    key TEXT NOT NULL PRIMARY KEY,
    value TEXT NOT NULL
);

-- One row per landmark template; a GeoPackage feature table whose geometry is the
-- footprint box. Column types are GeoPackage data types (FLOAT = 32-bit float,
-- DOUBLE = 64-bit). The pixel blob is the last column so that reads of the other
-- columns stop before it.
CREATE TABLE templates (
    fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
    geom POLYGON NOT NULL,
    level SMALLINT NOT NULL CHECK (level BETWEEN 0 AND 255),
    gsd_m DOUBLE NOT NULL,
    width_px INTEGER NOT NULL,
    height_px INTEGER NOT NULL,
    -- Centre: WGS84 geodetic, ellipsoidal height.
    lat_deg DOUBLE NOT NULL,
    lon_deg DOUBLE NOT NULL,
    h_m DOUBLE NOT NULL,
    -- The same centre in ECEF, denormalised for SQL users.
    ecef_x_m DOUBLE NOT NULL,
    ecef_y_m DOUBLE NOT NULL,
    ecef_z_m DOUBLE NOT NULL,
    -- Footprint box; footprint_min_lon_deg > footprint_max_lon_deg crosses the antimeridian.
    footprint_min_lon_deg DOUBLE NOT NULL,
    footprint_min_lat_deg DOUBLE NOT NULL,
    footprint_max_lon_deg DOUBLE NOT NULL,
    footprint_max_lat_deg DOUBLE NOT NULL,
    -- Terrain plane fit in the template's ENU frame.
    plane_normal_e DOUBLE NOT NULL,
    plane_normal_n DOUBLE NOT NULL,
    plane_normal_u DOUBLE NOT NULL,
    plane_residual_rms_m DOUBLE NOT NULL,
    -- n x n heights (m, relative to h_m), little-endian f32, row 0 north.
    height_grid_n INTEGER NOT NULL,
    height_grid_spacing_m DOUBLE NOT NULL,
    height_grid_heights_m BLOB NOT NULL
        CHECK (length(height_grid_heights_m) = 4 * height_grid_n * height_grid_n),
    shi_tomasi FLOAT NOT NULL,
    contrast_std FLOAT NOT NULL,
    second_peak_ncc FLOAT NOT NULL,
    -- Share of the contrast relief shading could make (0 albedo .. 1 shading).
    shading_share FLOAT NOT NULL,
    -- Index into the 'sources' metadata list.
    source INTEGER NOT NULL,
    -- 0: the ortho as imaged; k: rendered under the k-th entry of the 'suns' metadata.
    lighting SMALLINT NOT NULL CHECK (lighting BETWEEN 0 AND 255),
    -- Grey levels, u8, row-major, row 0 north; keep last.
    pixels BLOB NOT NULL CHECK (length(pixels) = width_px * height_px)
);

INSERT INTO gpkg_contents (table_name, data_type, identifier, description, srs_id)
VALUES ('templates', 'features', 'templates',
        'trn landmark templates: footprints of the north-up image patches', 4326);
INSERT INTO gpkg_geometry_columns VALUES ('templates', 'geom', 'POLYGON', 4326, 0, 0);

-- Per-level summary, written by DbWriter::finish so that LandmarkDb::levels
-- does not scan the templates. Registered as a GeoPackage attributes table: GIS users
-- see it next to the layer, and GDAL then lists only registered tables (not the
-- shadow tables of templates_rtree).
CREATE TABLE trn_levels (
    level INTEGER PRIMARY KEY NOT NULL,
    gsd_m DOUBLE NOT NULL,
    -- Largest template side (pixels): gsd_m * template_px is the level's footprint.
    template_px INTEGER NOT NULL,
    template_count INTEGER NOT NULL,
    min_lon_deg DOUBLE NOT NULL,
    min_lat_deg DOUBLE NOT NULL,
    max_lon_deg DOUBLE NOT NULL,
    max_lat_deg DOUBLE NOT NULL
);

INSERT INTO gpkg_contents (table_name, data_type, identifier, description)
VALUES ('trn_levels', 'attributes', 'trn_levels',
        'trn landmark pyramid levels: ground sample distance, template count, extent');

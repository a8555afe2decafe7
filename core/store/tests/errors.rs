//! Opening what is not a trn database, and refusing to overwrite files.

mod common;

use std::path::Path;

use common::{synthetic_template, write_db, Lcg};
use rusqlite::Connection;
use trn_store::{DbWriter, LandmarkDb, StoreError, StoreErrorKind, GPKG_APPLICATION_ID, SCHEMA_VERSION};

fn open_err(path: &Path) -> StoreError {
    let err = LandmarkDb::open(path).unwrap_err();
    let msg = err.to_string();
    assert!(msg.starts_with(&path.display().to_string()), "message does not name the path: {msg}");
    assert_eq!(err.path(), path);
    println!("{msg}");
    err
}

#[test]
fn open_missing_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("missing.gpkg");
    let err = open_err(&path);
    assert!(matches!(err.kind(), StoreErrorKind::NotFound));
    assert!(err.to_string().contains("no such file"));
    assert!(!path.exists(), "open must not create the file");
}

#[test]
fn open_text_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("notes.txt");
    std::fs::write(&path, "These are not the landmarks you are looking for.\n".repeat(100)).unwrap();
    let err = open_err(&path);
    assert!(matches!(err.kind(), StoreErrorKind::NotSqlite), "{err}");
    assert!(err.to_string().contains("not a SQLite database"));
}

#[test]
fn open_directory() {
    let dir = tempfile::tempdir().unwrap();
    let err = open_err(dir.path());
    assert!(err.to_string().contains("directory"));
}

#[test]
fn open_plain_sqlite_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("other.sqlite");
    let conn = Connection::open(&path).unwrap();
    conn.execute_batch("CREATE TABLE birds (name TEXT); INSERT INTO birds VALUES ('kea');").unwrap();
    drop(conn);
    let err = open_err(&path);
    assert!(matches!(err.kind(), StoreErrorKind::NotTrnDatabase(_)), "{err}");
    assert!(err.to_string().contains("application_id is 0x00000000"), "{err}");
}

#[test]
fn open_foreign_geopackage() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("roads.gpkg");
    let conn = Connection::open(&path).unwrap();
    conn.execute_batch(&format!(
        "PRAGMA application_id = {GPKG_APPLICATION_ID}; PRAGMA user_version = 10300; CREATE TABLE roads (fid INTEGER PRIMARY KEY);"
    ))
    .unwrap();
    drop(conn);
    let err = open_err(&path);
    assert!(err.to_string().contains("without the trn_metadata table"), "{err}");
}

#[test]
fn open_other_schema_version() {
    let dir = tempfile::tempdir().unwrap();
    let (path, _) = write_db(dir.path(), "old.gpkg", &mut []);
    let conn = Connection::open(&path).unwrap();
    conn.execute("UPDATE trn_metadata SET value = '999' WHERE key = 'schema_version'", []).unwrap();
    drop(conn);
    let err = open_err(&path);
    match err.kind() {
        StoreErrorKind::SchemaVersion { found, expected } => {
            assert_eq!((*found, *expected), (999, SCHEMA_VERSION))
        }
        _ => panic!("{err}"),
    }
}

#[test]
fn open_unfinished_database() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("partial.gpkg");
    let mut w = DbWriter::create(&path).unwrap();
    w.insert_batch(&mut [synthetic_template(&mut Lcg::new(5), 0, 0.0, 0.0)]).unwrap();
    drop(w);
    let err = open_err(&path);
    assert!(matches!(err.kind(), StoreErrorKind::Incomplete(_)), "{err}");
}

#[test]
fn create_refuses_existing_paths() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("precious.txt");
    std::fs::write(&path, "do not touch").unwrap();
    let err = DbWriter::create(&path).unwrap_err();
    assert!(matches!(err.kind(), StoreErrorKind::AlreadyExists), "{err}");
    assert!(err.to_string().starts_with(&path.display().to_string()), "{err}");
    assert_eq!(std::fs::read_to_string(&path).unwrap(), "do not touch");

    // Also an existing database, which stays readable and unchanged.
    let mut templates = vec![synthetic_template(&mut Lcg::new(6), 1, 0.0, 0.0)];
    let (db_path, _) = write_db(dir.path(), "db.gpkg", &mut templates);
    let before = std::fs::read(&db_path).unwrap();
    assert!(matches!(DbWriter::create(&db_path).unwrap_err().kind(), StoreErrorKind::AlreadyExists));
    assert_eq!(std::fs::read(&db_path).unwrap(), before);
    assert_eq!(LandmarkDb::open(&db_path).unwrap().count().unwrap(), 1);

    // A missing directory is an I/O error that names the path.
    let nested = dir.path().join("no/such/dir/x.gpkg");
    let err = DbWriter::create(&nested).unwrap_err();
    assert!(matches!(err.kind(), StoreErrorKind::Io(_)), "{err}");
    assert!(err.to_string().contains("no/such/dir/x.gpkg"), "{err}");
}

#[test]
fn paths_with_uri_characters_open_as_plain_paths() {
    // The file is opened through an SQLite URI (immutable=1): characters that
    // mean something in a URI must still name the file.
    let dir = tempfile::tempdir().unwrap();
    for name in ["a b%20c?immutable=0#x.gpkg", "ünï&cödé;=.gpkg", "%", "file:x.gpkg"] {
        let sub = dir.path().join(format!("d {name}"));
        std::fs::create_dir(&sub).unwrap();
        let mut templates = vec![synthetic_template(&mut Lcg::new(8), 0, 0.0, 0.0)];
        let (db_path, _) = write_db(&sub, name, &mut templates);
        let db = LandmarkDb::open(&db_path).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(db.count().unwrap(), 1, "{name}");
        assert_eq!(db.path(), db_path);
    }
    // A relative path, from the file's own directory.
    let mut templates = vec![synthetic_template(&mut Lcg::new(9), 0, 0.0, 0.0)];
    let (db_path, _) = write_db(dir.path(), "rel.gpkg", &mut templates);
    let cwd = std::env::current_dir().unwrap();
    let rel = pathdiff(&db_path, &cwd);
    assert_eq!(LandmarkDb::open(&rel).unwrap().count().unwrap(), 1, "{}", rel.display());
}

#[test]
fn an_open_database_keeps_reading_its_file_after_a_rename_over_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let mut old = vec![synthetic_template(&mut Lcg::new(10), 0, 0.0, 0.0)];
    let (path, _) = write_db(dir.path(), "db.gpkg", &mut old);
    let db = LandmarkDb::open(&path).unwrap();
    let mut new: Vec<_> = (0..3).map(|i| synthetic_template(&mut Lcg::new(11 + i), 0, 0.0, 0.0)).collect();
    let (next, _) = write_db(dir.path(), "next.gpkg", &mut new);
    std::fs::rename(&next, &path).unwrap();
    assert_eq!(db.count().unwrap(), 1);
    assert_eq!(db.for_each_template(|_| Ok(())).map(|_| ()).ok(), Some(()));
    assert_eq!(db.reopen().unwrap().count().unwrap(), 3);
}

/// `target` relative to `base` (both absolute), with `..` as needed.
fn pathdiff(target: &Path, base: &Path) -> std::path::PathBuf {
    let (t, b): (Vec<_>, Vec<_>) = (target.components().collect(), base.components().collect());
    let common = t.iter().zip(&b).take_while(|(x, y)| x == y).count();
    let mut out = std::path::PathBuf::new();
    for _ in common..b.len() {
        out.push("..");
    }
    for c in &t[common..] {
        out.push(c);
    }
    out
}

//! Map tiles under a station's map, in the usual web-map grid (Web Mercator, `{z}/{x}/{y}`,
//! 256 px, y down from the north): by default OpenStreetMap's tile server (with its credit),
//! which the browser loads; or another `http(s)://` URL template; or served by the station
//! itself, so the page works offline on a field laptop, from a local directory template
//! (`/maps/field/{z}/{x}/{y}.png`) or an MBTiles file (SQLite, raster tiles, TMS rows flipped
//! to XYZ here); or none (`--tiles none`). Whatever the choice, a page that cannot load a tile
//! draws its metric grid there and says the tiles are unreachable.

use std::path::PathBuf;

use serde::Serialize;

/// OpenStreetMap's tile server: the default map.
pub const OSM_TEMPLATE: &str = "https://tile.openstreetmap.org/{z}/{x}/{y}.png";
/// The credit OpenStreetMap's tiles must carry.
pub const OSM_ATTRIBUTION: &str = "© OpenStreetMap contributors";

/// What `--tiles` takes besides a template or a file: OpenStreetMap's tiles (the default).
pub const CHOICE_OSM: &str = "osm";
/// What `--tiles` takes besides a template or a file: no tiles, the grid alone.
pub const CHOICE_NONE: &str = "none";

/// The content type of an image file, by its extension.
pub fn content_type(path: &std::path::Path) -> &'static str {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("png") => "image/png",
        Some("jpg" | "jpeg") => "image/jpeg",
        Some("gif") => "image/gif",
        Some("webp") => "image/webp",
        Some("svg") => "image/svg+xml",
        _ => "application/octet-stream",
    }
}

/// The deepest zoom level accepted in a tile request (a 2^30-tile grid is far past any map).
const MAX_ZOOM: u32 = 30;

/// Where map tiles come from.
#[derive(Debug)]
pub enum TileSource {
    /// An `http(s)://` template with `{z}`, `{x}` and `{y}` the browser fills and loads.
    Remote(String),
    /// A local path template with `{z}`, `{x}` and `{y}`, served at `/api/tiles/{z}/{x}/{y}`.
    Directory(String),
    /// An MBTiles file, served at `/api/tiles/{z}/{x}/{y}`.
    MbTiles {
        /// The file.
        path: PathBuf,
        /// Read-only connection; SQLite calls are blocking, so callers use a blocking thread.
        db: std::sync::Mutex<rusqlite::Connection>,
        /// The tiles' content type (from the metadata's `format`).
        content_type: &'static str,
    },
}

/// Map tiles drawn under the plan.
#[derive(Debug)]
pub struct Tiles {
    /// Their source.
    pub source: TileSource,
    /// Zoom levels available.
    pub min_zoom: u32,
    /// Zoom levels available.
    pub max_zoom: u32,
    /// Area covered, `[west, south, east, north]` degrees, when known (MBTiles metadata).
    pub bounds: Option<[f64; 4]>,
    /// Credit shown under the map (MBTiles `attribution`), when known.
    pub attribution: Option<String>,
}

/// What the page gets about the tiles (`GET /api/config`, `tiles`).
#[derive(Clone, Debug, Serialize)]
pub struct TilesView {
    /// The URL template the page fills with `{z}`, `{x}` and `{y}`.
    pub url: String,
    /// Least zoom level.
    pub minzoom: u32,
    /// Greatest zoom level.
    pub maxzoom: u32,
    /// `[west, south, east, north]`, degrees, when known.
    pub bounds: Option<[f64; 4]>,
    /// Credit to show.
    pub attribution: Option<String>,
}

/// The route the station serves its tiles at.
pub const TILE_ROUTE: &str = "/api/tiles/{z}/{x}/{y}";

/// Why the tiles named by the operator cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum TilesOpenError {
    /// A template without all of `{z}`, `{x}` and `{y}`.
    #[error("tile template `{0}` must contain {{z}}, {{x}} and {{y}} (or name an .mbtiles file)")]
    Template(String),
    /// The MBTiles file cannot be opened or read as one.
    #[error("MBTiles {path}: {reason}")]
    MbTiles {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The tiles are vector tiles, which the page cannot draw.
    #[error("MBTiles {0}: vector tiles (format pbf) are not supported; use raster tiles (png, jpg, webp)")]
    Vector(PathBuf),
}

impl Tiles {
    /// Tiles from what the operator named: a file ending in `.mbtiles`, or a template with
    /// `{z}`, `{x}` and `{y}` (an `http(s)://` URL, or a local path).
    ///
    /// # Errors
    /// A template missing a placeholder; an MBTiles file that cannot be read, has no `tiles`
    /// table, or holds vector tiles.
    pub fn open(spec: &str) -> Result<Self, TilesOpenError> {
        if spec.to_ascii_lowercase().ends_with(".mbtiles") {
            return Self::open_mbtiles(std::path::Path::new(spec));
        }
        if !["{z}", "{x}", "{y}"].iter().all(|p| spec.contains(p)) {
            return Err(TilesOpenError::Template(spec.to_owned()));
        }
        let source = if spec.starts_with("http://") || spec.starts_with("https://") {
            TileSource::Remote(spec.to_owned())
        } else {
            TileSource::Directory(spec.to_owned())
        };
        Ok(Self {
            source,
            min_zoom: 0,
            max_zoom: 19,
            bounds: None,
            attribution: None,
        })
    }

    /// The tiles `--tiles` names: [`CHOICE_OSM`] (OpenStreetMap's, the default),
    /// [`CHOICE_NONE`] (none: the page draws its grid), or what [`Tiles::open`] takes;
    /// `attribution`, when given, is the credit shown under the map (OpenStreetMap's tiles
    /// carry theirs without it).
    ///
    /// # Errors
    /// As [`Tiles::open`].
    pub fn choose(spec: &str, attribution: Option<&str>) -> Result<Option<Self>, TilesOpenError> {
        let mut tiles = match spec.trim() {
            CHOICE_NONE => return Ok(None),
            CHOICE_OSM => Self::open(OSM_TEMPLATE)?,
            other => Self::open(other)?,
        };
        if let Some(a) = attribution {
            tiles.attribution = Some(a.to_owned());
        } else if matches!(&tiles.source, TileSource::Remote(t) if t.contains("tile.openstreetmap.org/"))
        {
            tiles.attribution = Some(OSM_ATTRIBUTION.to_owned());
        }
        Ok(Some(tiles))
    }

    fn open_mbtiles(path: &std::path::Path) -> Result<Self, TilesOpenError> {
        use rusqlite::OpenFlags;
        let fail = |reason: String| TilesOpenError::MbTiles {
            path: path.to_owned(),
            reason,
        };
        if !path.is_file() {
            return Err(fail("no such file".into()));
        }
        let db = rusqlite::Connection::open_with_flags(
            path,
            OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )
        .map_err(|e| fail(e.to_string()))?;
        let meta = |name: &str| -> Option<String> {
            db.query_row("SELECT value FROM metadata WHERE name = ?1", [name], |r| {
                r.get::<_, String>(0)
            })
            .ok()
        };
        let format = meta("format").unwrap_or_else(|| "png".into());
        let content_type = match format.to_ascii_lowercase().as_str() {
            "png" => "image/png",
            "jpg" | "jpeg" => "image/jpeg",
            "webp" => "image/webp",
            "pbf" | "mvt" => return Err(TilesOpenError::Vector(path.to_owned())),
            other => return Err(fail(format!("unknown tile format `{other}`"))),
        };
        let (lo, hi): (Option<u32>, Option<u32>) = db
            .query_row(
                "SELECT MIN(zoom_level), MAX(zoom_level) FROM tiles",
                [],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
            .map_err(|e| fail(format!("not an MBTiles file (its `tiles` table: {e})")))?;
        let number = |name: &str| meta(name).and_then(|v| v.trim().parse::<u32>().ok());
        let (Some(lo), Some(hi)) = (number("minzoom").or(lo), number("maxzoom").or(hi)) else {
            return Err(fail("it holds no tiles".into()));
        };
        let bounds = meta("bounds").and_then(|b| {
            let v: Vec<f64> = b.split(',').filter_map(|x| x.trim().parse().ok()).collect();
            match v[..] {
                [w, s, e, n] if [w, s, e, n].iter().all(|x| x.is_finite()) => Some([w, s, e, n]),
                _ => None,
            }
        });
        Ok(Self {
            min_zoom: lo.min(MAX_ZOOM),
            max_zoom: hi.min(MAX_ZOOM),
            bounds,
            attribution: meta("attribution"),
            source: TileSource::MbTiles {
                path: path.to_owned(),
                db: std::sync::Mutex::new(db),
                content_type,
            },
        })
    }

    /// The page's view.
    pub fn view(&self) -> TilesView {
        TilesView {
            url: match &self.source {
                TileSource::Remote(t) => t.clone(),
                TileSource::Directory(_) | TileSource::MbTiles { .. } => TILE_ROUTE.into(),
            },
            minzoom: self.min_zoom,
            maxzoom: self.max_zoom,
            bounds: self.bounds,
            attribution: self.attribution.clone(),
        }
    }

    /// Tile `z/x/y` (XYZ, y down from the north) and its content type; `Ok(None)` when the
    /// station does not have it (or does not serve tiles). Blocking: SQLite or file I/O.
    ///
    /// # Errors
    /// Reading the file or the database failed.
    pub fn tile(&self, z: u32, x: u32, y: u32) -> Result<Option<(Vec<u8>, &'static str)>, String> {
        if z > MAX_ZOOM || u64::from(x) >= 1u64 << z || u64::from(y) >= 1u64 << z {
            return Ok(None);
        }
        match &self.source {
            TileSource::Remote(_) => Ok(None),
            TileSource::Directory(template) => {
                // Only numbers are put into the operator's template: no path from the request.
                let path = PathBuf::from(
                    template
                        .replace("{z}", &z.to_string())
                        .replace("{x}", &x.to_string())
                        .replace("{y}", &y.to_string()),
                );
                match std::fs::read(&path) {
                    Ok(b) => Ok(Some((b, content_type(&path)))),
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
                    Err(e) => Err(format!("tile {}: {e}", path.display())),
                }
            }
            TileSource::MbTiles {
                path,
                db,
                content_type,
            } => {
                // MBTiles rows count from the south (TMS).
                let row = (1u64 << z) - 1 - u64::from(y);
                let db = db.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
                let r = db.query_row(
                    "SELECT tile_data FROM tiles WHERE zoom_level = ?1 AND tile_column = ?2 AND tile_row = ?3",
                    rusqlite::params![z, x, row],
                    |r| r.get::<_, Vec<u8>>(0),
                );
                match r {
                    Ok(b) => Ok(Some((b, *content_type))),
                    Err(rusqlite::Error::QueryReturnedNoRows) => Ok(None),
                    Err(e) => Err(format!("MBTiles {}: {e}", path.display())),
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An MBTiles file made here: two tiles, one at zoom 1 and one at zoom 3.
    pub(crate) fn mbtiles(path: &std::path::Path, format: &str) {
        let db = rusqlite::Connection::open(path).unwrap();
        db.execute_batch(
            "CREATE TABLE metadata (name TEXT, value TEXT);
             CREATE TABLE tiles (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER, tile_data BLOB);",
        )
        .unwrap();
        for (k, v) in [
            ("format", format),
            ("bounds", "1.98,41.27,1.99,41.28"),
            ("attribution", "test"),
        ] {
            db.execute("INSERT INTO metadata VALUES (?1, ?2)", [k, v])
                .unwrap();
        }
        // XYZ 1/1/0 is TMS row 1; XYZ 3/4/2 is TMS row 5.
        db.execute("INSERT INTO tiles VALUES (1, 1, 1, x'0102')", [])
            .unwrap();
        db.execute("INSERT INTO tiles VALUES (3, 4, 5, x'0304')", [])
            .unwrap();
    }

    #[test]
    fn mbtiles_rows_are_flipped_and_vector_tiles_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.mbtiles");
        mbtiles(&p, "png");
        let t = Tiles::open(&p.display().to_string()).unwrap();
        assert_eq!((t.min_zoom, t.max_zoom), (1, 3));
        assert_eq!(t.bounds, Some([1.98, 41.27, 1.99, 41.28]));
        assert_eq!(t.view().url, TILE_ROUTE);
        assert_eq!(t.tile(1, 1, 0).unwrap(), Some((vec![1, 2], "image/png")));
        assert_eq!(t.tile(3, 4, 2).unwrap(), Some((vec![3, 4], "image/png")));
        assert_eq!(t.tile(3, 4, 5).unwrap(), None);
        assert_eq!(t.tile(1, 2, 0).unwrap(), None, "x outside the grid");
        assert_eq!(t.tile(31, 0, 0).unwrap(), None);
        let v = dir.path().join("v.mbtiles");
        mbtiles(&v, "pbf");
        assert!(matches!(
            Tiles::open(&v.display().to_string()),
            Err(TilesOpenError::Vector(_))
        ));
        let junk = dir.path().join("junk.mbtiles");
        std::fs::write(&junk, "not sqlite").unwrap();
        assert!(Tiles::open(&junk.display().to_string()).is_err());
        assert!(Tiles::open("/nonexistent.mbtiles").is_err());
    }

    #[test]
    fn openstreetmap_by_default_with_its_credit_and_none_for_the_grid() {
        let osm = Tiles::choose(CHOICE_OSM, None).unwrap().unwrap();
        assert_eq!(osm.view().url, OSM_TEMPLATE);
        assert_eq!(osm.view().attribution.as_deref(), Some(OSM_ATTRIBUTION));
        assert!(Tiles::choose(CHOICE_NONE, None).unwrap().is_none());
        let own = Tiles::choose("https://t.example/{z}/{x}/{y}.png", Some("© us"))
            .unwrap()
            .unwrap();
        assert_eq!(own.view().attribution.as_deref(), Some("© us"));
        let bare = Tiles::choose("https://t.example/{z}/{x}/{y}.png", None)
            .unwrap()
            .unwrap();
        assert_eq!(bare.view().attribution, None);
        assert!(Tiles::choose("https://t.example/{z}.png", None).is_err());
    }

    #[test]
    fn templates_need_every_placeholder() {
        let r = Tiles::open("https://tile.example.org/{z}/{x}/{y}.png").unwrap();
        assert_eq!(r.view().url, "https://tile.example.org/{z}/{x}/{y}.png");
        assert_eq!(r.tile(1, 0, 0).unwrap(), None);
        assert!(matches!(
            Tiles::open("https://a/{z}/{x}.png"),
            Err(TilesOpenError::Template(_))
        ));
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("2/1")).unwrap();
        std::fs::write(dir.path().join("2/1/3.png"), [9u8]).unwrap();
        let local =
            Tiles::open(&format!("{}/{{z}}/{{x}}/{{y}}.png", dir.path().display())).unwrap();
        assert_eq!(local.view().url, TILE_ROUTE);
        assert_eq!(local.tile(2, 1, 3).unwrap(), Some((vec![9], "image/png")));
        assert_eq!(local.tile(2, 1, 2).unwrap(), None);
    }
}

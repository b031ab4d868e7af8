//! A georeferenced image drawn under the plan (an aerial photo of the field, a site plan):
//! north up, its edges on two parallels and two meridians; the station serves a local file, or
//! the page loads a URL the operator gives ([`Background`]). The map tiles under it are every
//! station's ([`station_web::tiles`]).

use std::path::PathBuf;

use serde::Serialize;
pub use station_web::tiles::content_type;

/// Where the image comes from.
#[derive(Clone, Debug, PartialEq)]
pub enum BackgroundSource {
    /// A file on the station's machine, served at `/api/background`.
    File(PathBuf),
    /// An `http://` or `https://` URL the browser loads itself.
    Url(String),
}

/// A georeferenced background image.
#[derive(Clone, Debug, PartialEq)]
pub struct Background {
    /// The image.
    pub source: BackgroundSource,
    /// Latitude of the top edge, degrees.
    pub north: f64,
    /// Longitude of the left edge, degrees.
    pub west: f64,
    /// Latitude of the bottom edge, degrees.
    pub south: f64,
    /// Longitude of the right edge, degrees.
    pub east: f64,
}

/// What the page gets (`GET /api/config`).
#[derive(Clone, Debug, Serialize)]
pub struct BackgroundView {
    /// Where the page loads the image from.
    pub url: String,
    /// Edges, degrees.
    pub north: f64,
    /// Edges, degrees.
    pub west: f64,
    /// Edges, degrees.
    pub south: f64,
    /// Edges, degrees.
    pub east: f64,
}

impl Background {
    /// A background from the image (`FILE` or `http(s)://URL`) and its bounds as
    /// `NORTH,WEST,SOUTH,EAST` in degrees (the top-left and bottom-right corners).
    ///
    /// # Errors
    /// Bounds that are not four numbers, out of range, empty, or crossing the antimeridian.
    pub fn parse(image: &str, bounds: &str) -> Result<Self, String> {
        let n: Vec<f64> = bounds
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| format!("background bounds `{bounds}`: {e}"))?;
        let [north, west, south, east] = n[..] else {
            return Err(format!(
                "background bounds `{bounds}`: expected NORTH,WEST,SOUTH,EAST (4 numbers)"
            ));
        };
        let lat_ok = |x: f64| x.is_finite() && (-90.0..=90.0).contains(&x);
        let lon_ok = |x: f64| x.is_finite() && (-180.0..=180.0).contains(&x);
        if !(lat_ok(north) && lat_ok(south) && lon_ok(west) && lon_ok(east)) {
            return Err(format!("background bounds `{bounds}`: out of range"));
        }
        if north <= south || east <= west {
            return Err(format!(
                "background bounds `{bounds}`: north must exceed south and east exceed west \
                 (images across the antimeridian are not supported)"
            ));
        }
        let source = if image.starts_with("http://") || image.starts_with("https://") {
            BackgroundSource::Url(image.to_owned())
        } else {
            BackgroundSource::File(PathBuf::from(image))
        };
        Ok(Self {
            source,
            north,
            west,
            south,
            east,
        })
    }

    /// The page's view.
    pub fn view(&self) -> BackgroundView {
        BackgroundView {
            url: match &self.source {
                BackgroundSource::File(_) => "/api/background".into(),
                BackgroundSource::Url(u) => u.clone(),
            },
            north: self.north,
            west: self.west,
            south: self.south,
            east: self.east,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_and_sources() {
        let b = Background::parse("field.png", "41.2765, 1.9865, 41.2745,1.9885").unwrap();
        assert_eq!(b.source, BackgroundSource::File("field.png".into()));
        assert_eq!(
            (b.north, b.west, b.south, b.east),
            (41.2765, 1.9865, 41.2745, 1.9885)
        );
        assert_eq!(b.view().url, "/api/background");
        let u = Background::parse("https://example.org/a.jpg", "1,1,0,2").unwrap();
        assert_eq!(u.view().url, "https://example.org/a.jpg");
        for bad in [
            "1,2,3",
            "a,b,c,d",
            "0,1,1,2",
            "1,2,0,1",
            "95,0,0,1",
            "1,0,0,200",
            "NaN,0,0,1",
        ] {
            assert!(Background::parse("x.png", bad).is_err(), "{bad}");
        }
        assert_eq!(content_type("a/B.JPG".as_ref()), "image/jpeg");
        assert_eq!(content_type("a".as_ref()), "application/octet-stream");
    }
}

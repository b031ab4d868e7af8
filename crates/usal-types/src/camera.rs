//! A downward-looking camera on a vehicle (the Broz search's, seeds 000 and 002): its frames and
//! the geometry that ties a pixel to the ground. The simulator renders with it, the stations
//! mark points with it, so both agree on where a pixel is.
//!
//! The camera looks straight down (nadir); the top of the picture points along the vehicle's
//! heading. At height `h` above the ground with a horizontal field of view `hfov`, the picture
//! covers `2 h tan(hfov / 2)` metres across, and proportionally along.

use serde::{Deserialize, Serialize};

/// Metres per degree of latitude (and of longitude at the equator): the flat-earth
/// approximation every USAL map uses over a few kilometres.
const M_PER_DEG: f64 = 111_319.49;

/// The lowest a camera is taken to be above the ground, metres: a rover's camera on its mast.
pub const MIN_CAMERA_HEIGHT_M: f64 = 2.0;

/// Parses a picture size `WxH` (e.g. `320x240`, each 16-1920 pixels).
///
/// # Errors
/// What is wrong with `s`.
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}` is not WIDTHxHEIGHT (e.g. 320x240)"))?;
    let dim = |v: &str| -> Result<u32, String> {
        v.trim()
            .parse::<u32>()
            .ok()
            .filter(|n| (16..=1920).contains(n))
            .ok_or_else(|| format!("`{v}` in `{s}` is not a size from 16 to 1920 pixels"))
    };
    Ok((dim(w)?, dim(h)?))
}

/// Where a camera is and how it looks: what a frame's pixels mean on the ground.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraPose {
    /// The vehicle's latitude, degrees.
    pub lat: f64,
    /// The vehicle's longitude, degrees.
    pub lon: f64,
    /// Height above the ground (home), metres.
    pub height_m: f64,
    /// The vehicle's heading, degrees from north, clockwise: the picture's up.
    pub heading_deg: f64,
    /// Horizontal field of view, degrees.
    pub hfov_deg: f64,
}

impl CameraPose {
    /// The ground covered, `(across, along)` metres, by a `width` × `height` picture.
    pub fn footprint(&self, width: u32, height: u32) -> (f64, f64) {
        let h = self.height_m.max(MIN_CAMERA_HEIGHT_M);
        let across = 2.0 * h * (self.hfov_deg.to_radians() / 2.0).tan();
        (across, across * f64::from(height) / f64::from(width.max(1)))
    }

    /// Where the centre of pixel `(x, y)` of a `width` × `height` picture is on the ground,
    /// metres `(north, east)` of the vehicle.
    pub fn ground_offset(&self, x: f64, y: f64, width: u32, height: u32) -> (f64, f64) {
        let (across, along) = self.footprint(width, height);
        let right = ((x + 0.5) / f64::from(width.max(1)) - 0.5) * across;
        let forward = (0.5 - (y + 0.5) / f64::from(height.max(1))) * along;
        let (s, c) = self.heading_deg.to_radians().sin_cos();
        (forward * c - right * s, forward * s + right * c)
    }

    /// Where the centre of pixel `(x, y)` is, `(lat, lon)` degrees.
    pub fn ground_point(&self, x: f64, y: f64, width: u32, height: u32) -> (f64, f64) {
        let (north, east) = self.ground_offset(x, y, width, height);
        let k = self.lat.to_radians().cos().max(1e-6);
        (
            self.lat + north / M_PER_DEG,
            self.lon + east / (M_PER_DEG * k),
        )
    }
}

/// One frame of a vehicle's camera (the camera service's `frame` and `raw` variables).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraFrame {
    /// Frame number since the camera started.
    pub seq: u64,
    /// When it was taken: milliseconds since the Unix epoch (the camera host's clock).
    pub taken_unix_ms: u64,
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// `jpeg`, or `rgb8` (rows top to bottom, 3 bytes a pixel).
    pub format: String,
    /// The picture in `format`.
    pub data: Vec<u8>,
    /// Where the camera was and how it looked.
    pub pose: CameraPose,
}

impl CameraFrame {
    /// Where the centre of pixel `(x, y)` of this frame is, `(lat, lon)` degrees; `None`
    /// outside the picture.
    pub fn ground_point(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let inside =
            (0.0..f64::from(self.width)).contains(&x) && (0.0..f64::from(self.height)).contains(&y);
        inside.then(|| self.pose.ground_point(x, y, self.width, self.height))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(heading_deg: f64) -> CameraPose {
        CameraPose {
            lat: 41.275,
            lon: 1.987,
            height_m: 30.0,
            heading_deg,
            hfov_deg: 90.0,
        }
    }

    fn close(a: (f64, f64), b: (f64, f64)) -> bool {
        (a.0 - b.0).abs() < 1e-6 && (a.1 - b.1).abs() < 1e-6
    }

    #[test]
    fn the_footprint_grows_with_height_and_follows_the_picture_shape() {
        let (across, along) = pose(0.0).footprint(400, 300);
        assert!((across - 60.0).abs() < 1e-9, "{across}");
        assert!((along - 45.0).abs() < 1e-9, "{along}");
        let low = CameraPose {
            height_m: 0.0,
            ..pose(0.0)
        };
        assert!(
            (low.footprint(400, 300).0 - 4.0).abs() < 1e-9,
            "a mast's height at least"
        );
    }

    #[test]
    fn the_top_of_the_picture_is_ahead_and_its_right_is_to_the_right() {
        // Heading north: the top middle is north, the middle right east.
        let (n, e) = pose(0.0).ground_offset(199.5, -0.5, 400, 300);
        assert!(close((n, e), (22.5, 0.0)), "{n} {e}");
        let (n, e) = pose(0.0).ground_offset(399.5, 149.5, 400, 300);
        assert!(close((n, e), (0.0, 30.0)), "{n} {e}");
        // Heading east: the top is east, the right is south.
        let (n, e) = pose(90.0).ground_offset(199.5, -0.5, 400, 300);
        assert!(close((n, e), (0.0, 22.5)), "{n} {e}");
        let (n, e) = pose(90.0).ground_offset(399.5, 149.5, 400, 300);
        assert!(close((n, e), (-30.0, 0.0)), "{n} {e}");
    }

    #[test]
    fn a_size_is_width_x_height_in_range() {
        assert_eq!(parse_size("320x240"), Ok((320, 240)));
        assert_eq!(parse_size("64X48"), Ok((64, 48)));
        assert!(parse_size("320").unwrap_err().contains("not WIDTHxHEIGHT"));
        assert!(parse_size("8x8").unwrap_err().contains("16 to 1920"));
        assert!(parse_size("axb").is_err());
    }

    #[test]
    fn a_pixel_is_a_point_on_the_map_and_none_outside_the_picture() {
        let f = CameraFrame {
            width: 400,
            height: 300,
            pose: pose(0.0),
            ..CameraFrame::default()
        };
        let (lat, lon) = f.ground_point(199.5, 149.5).expect("the centre");
        assert!(close((lat, lon), (41.275, 1.987)));
        let (lat, _) = f.ground_point(199.5, 0.0).expect("the top row");
        let north = (0.5 - 0.5 / 300.0) * 45.0;
        assert!((lat - 41.275 - north / M_PER_DEG).abs() < 1e-9);
        assert_eq!(f.ground_point(400.0, 10.0), None);
        assert_eq!(f.ground_point(-1.0, 10.0), None);
    }
}

//! WGS-84 geodesy (Vincenty inverse and direct problems) and the local east/north frame that
//! every pattern (hold, scan, perimeter, arc) is computed in.
//!
//! Vincenty's iterative formulae are accurate to well below a millimetre on the ellipsoid for
//! the distances a flight plan uses. They fail to converge only for nearly antipodal points
//! (half the Earth apart), which no plan contains; there we fall back to a great circle on the
//! mean-radius sphere rather than fail, so the functions are total.

use serde::{Deserialize, Serialize};

/// WGS-84 semi-major axis, metres.
pub const WGS84_A: f64 = 6_378_137.0;
/// WGS-84 flattening.
pub const WGS84_F: f64 = 1.0 / 298.257_223_563;
/// WGS-84 semi-minor axis, metres.
pub const WGS84_B: f64 = WGS84_A * (1.0 - WGS84_F);
const MEAN_RADIUS: f64 = 6_371_008.8;

/// A horizontal position in degrees (WGS-84).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeoPoint {
    /// Latitude, degrees north.
    pub lat: f64,
    /// Longitude, degrees east.
    pub lon: f64,
}

impl GeoPoint {
    /// A point from latitude and longitude in degrees.
    pub const fn new(lat: f64, lon: f64) -> Self {
        Self { lat, lon }
    }
}

/// The answer to the inverse problem.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Inverse {
    /// Ellipsoidal distance, metres.
    pub distance: f64,
    /// Forward azimuth at the first point, degrees clockwise from north in [0, 360).
    pub azi1: f64,
    /// Forward azimuth at the second point, degrees in [0, 360).
    pub azi2: f64,
}

/// Wraps an angle in degrees to [0, 360).
pub fn wrap360(deg: f64) -> f64 {
    let w = deg.rem_euclid(360.0);
    if w >= 360.0 {
        0.0
    } else {
        w
    }
}

/// Wraps an angle in degrees to (-180, 180].
pub fn wrap180(deg: f64) -> f64 {
    let w = wrap360(deg);
    if w > 180.0 {
        w - 360.0
    } else {
        w
    }
}

fn wrap_pi(rad: f64) -> f64 {
    let two_pi = 2.0 * std::f64::consts::PI;
    let w = (rad + std::f64::consts::PI).rem_euclid(two_pi) - std::f64::consts::PI;
    if w <= -std::f64::consts::PI {
        w + two_pi
    } else {
        w
    }
}

/// Distance and azimuths from `p1` to `p2` on the WGS-84 ellipsoid.
pub fn inverse(p1: GeoPoint, p2: GeoPoint) -> Inverse {
    let (a, b, f) = (WGS84_A, WGS84_B, WGS84_F);
    let l = wrap_pi((p2.lon - p1.lon).to_radians());
    let u1 = ((1.0 - f) * p1.lat.to_radians().tan()).atan();
    let u2 = ((1.0 - f) * p2.lat.to_radians().tan()).atan();
    let (su1, cu1) = u1.sin_cos();
    let (su2, cu2) = u2.sin_cos();
    let mut lambda = l;
    for _ in 0..200 {
        let (sl, cl) = lambda.sin_cos();
        let sin_sigma = ((cu2 * sl).powi(2) + (cu1 * su2 - su1 * cu2 * cl).powi(2)).sqrt();
        if sin_sigma == 0.0 {
            return Inverse {
                distance: 0.0,
                azi1: 0.0,
                azi2: 0.0,
            };
        }
        let cos_sigma = su1 * su2 + cu1 * cu2 * cl;
        let sigma = sin_sigma.atan2(cos_sigma);
        let sin_alpha = cu1 * cu2 * sl / sin_sigma;
        let cos2_alpha = 1.0 - sin_alpha * sin_alpha;
        let cos2sm = if cos2_alpha.abs() > 1e-300 {
            cos_sigma - 2.0 * su1 * su2 / cos2_alpha
        } else {
            0.0
        };
        let c = f / 16.0 * cos2_alpha * (4.0 + f * (4.0 - 3.0 * cos2_alpha));
        let prev = lambda;
        lambda = l
            + (1.0 - c)
                * f
                * sin_alpha
                * (sigma
                    + c * sin_sigma * (cos2sm + c * cos_sigma * (-1.0 + 2.0 * cos2sm * cos2sm)));
        if (lambda - prev).abs() < 1e-13 {
            let u_sq = cos2_alpha * (a * a - b * b) / (b * b);
            let big_a =
                1.0 + u_sq / 16384.0 * (4096.0 + u_sq * (-768.0 + u_sq * (320.0 - 175.0 * u_sq)));
            let big_b = u_sq / 1024.0 * (256.0 + u_sq * (-128.0 + u_sq * (74.0 - 47.0 * u_sq)));
            let d_sigma = big_b
                * sin_sigma
                * (cos2sm
                    + big_b / 4.0
                        * (cos_sigma * (-1.0 + 2.0 * cos2sm * cos2sm)
                            - big_b / 6.0
                                * cos2sm
                                * (-3.0 + 4.0 * sin_sigma * sin_sigma)
                                * (-3.0 + 4.0 * cos2sm * cos2sm)));
            let (sl, cl) = lambda.sin_cos();
            let azi1 = (cu2 * sl).atan2(cu1 * su2 - su1 * cu2 * cl);
            let azi2 = (cu1 * sl).atan2(-su1 * cu2 + cu1 * su2 * cl);
            return Inverse {
                distance: b * big_a * (sigma - d_sigma),
                azi1: wrap360(azi1.to_degrees()),
                azi2: wrap360(azi2.to_degrees()),
            };
        }
    }
    spherical_inverse(p1, p2)
}

fn spherical_inverse(p1: GeoPoint, p2: GeoPoint) -> Inverse {
    let (f1, f2) = (p1.lat.to_radians(), p2.lat.to_radians());
    let dl = (p2.lon - p1.lon).to_radians();
    let h = ((f2 - f1) / 2.0).sin().powi(2) + f1.cos() * f2.cos() * (dl / 2.0).sin().powi(2);
    let d = 2.0 * MEAN_RADIUS * h.sqrt().min(1.0).asin();
    let y = dl.sin() * f2.cos();
    let x = f1.cos() * f2.sin() - f1.sin() * f2.cos() * dl.cos();
    let y2 = dl.sin() * f1.cos();
    let x2 = -f2.cos() * f1.sin() + f2.sin() * f1.cos() * dl.cos();
    Inverse {
        distance: d,
        azi1: wrap360(y.atan2(x).to_degrees()),
        azi2: wrap360(y2.atan2(x2).to_degrees()),
    }
}

/// The point `distance` metres from `p` along the geodesic starting at azimuth `azi_deg`.
pub fn direct(p: GeoPoint, azi_deg: f64, distance: f64) -> GeoPoint {
    let (a, b, f) = (WGS84_A, WGS84_B, WGS84_F);
    let alpha1 = azi_deg.to_radians();
    let (sa1, ca1) = alpha1.sin_cos();
    let tan_u1 = (1.0 - f) * p.lat.to_radians().tan();
    let cu1 = 1.0 / (1.0 + tan_u1 * tan_u1).sqrt();
    let su1 = tan_u1 * cu1;
    let sigma1 = tan_u1.atan2(ca1);
    let sin_alpha = cu1 * sa1;
    let cos2_alpha = 1.0 - sin_alpha * sin_alpha;
    let u_sq = cos2_alpha * (a * a - b * b) / (b * b);
    let big_a = 1.0 + u_sq / 16384.0 * (4096.0 + u_sq * (-768.0 + u_sq * (320.0 - 175.0 * u_sq)));
    let big_b = u_sq / 1024.0 * (256.0 + u_sq * (-128.0 + u_sq * (74.0 - 47.0 * u_sq)));
    let mut sigma = distance / (b * big_a);
    let mut cos2sm = (2.0 * sigma1 + sigma).cos();
    for _ in 0..200 {
        cos2sm = (2.0 * sigma1 + sigma).cos();
        let (ss, cs) = sigma.sin_cos();
        let d_sigma = big_b
            * ss
            * (cos2sm
                + big_b / 4.0
                    * (cs * (-1.0 + 2.0 * cos2sm * cos2sm)
                        - big_b / 6.0
                            * cos2sm
                            * (-3.0 + 4.0 * ss * ss)
                            * (-3.0 + 4.0 * cos2sm * cos2sm)));
        let prev = sigma;
        sigma = distance / (b * big_a) + d_sigma;
        if (sigma - prev).abs() < 1e-13 {
            break;
        }
    }
    let (ss, cs) = sigma.sin_cos();
    let tmp = su1 * ss - cu1 * cs * ca1;
    let lat =
        (su1 * cs + cu1 * ss * ca1).atan2((1.0 - f) * (sin_alpha * sin_alpha + tmp * tmp).sqrt());
    let lambda = (ss * sa1).atan2(cu1 * cs - su1 * ss * ca1);
    let c = f / 16.0 * cos2_alpha * (4.0 + f * (4.0 - 3.0 * cos2_alpha));
    let l = lambda
        - (1.0 - c)
            * f
            * sin_alpha
            * (sigma + c * ss * (cos2sm + c * cs * (-1.0 + 2.0 * cos2sm * cos2sm)));
    GeoPoint {
        lat: lat.to_degrees(),
        lon: wrap180(p.lon + l.to_degrees()),
    }
}

/// Geodesic distance in metres.
pub fn distance(p1: GeoPoint, p2: GeoPoint) -> f64 {
    inverse(p1, p2).distance
}

/// A point in a local frame: metres east and north of the frame's origin.
#[derive(Clone, Copy, Debug, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Xy {
    /// Metres east.
    pub e: f64,
    /// Metres north.
    pub n: f64,
}

impl Xy {
    /// A local point.
    pub const fn new(e: f64, n: f64) -> Self {
        Self { e, n }
    }
    /// Sum.
    pub fn plus(self, o: Xy) -> Xy {
        Xy::new(self.e + o.e, self.n + o.n)
    }
    /// Difference.
    pub fn minus(self, o: Xy) -> Xy {
        Xy::new(self.e - o.e, self.n - o.n)
    }
    /// Scaled by `k`.
    pub fn scale(self, k: f64) -> Xy {
        Xy::new(self.e * k, self.n * k)
    }
    /// Dot product.
    pub fn dot(self, o: Xy) -> f64 {
        self.e * o.e + self.n * o.n
    }
    /// z of the cross product.
    pub fn cross(self, o: Xy) -> f64 {
        self.e * o.n - self.n * o.e
    }
    /// Euclidean length.
    pub fn norm(self) -> f64 {
        self.e.hypot(self.n)
    }
    /// The unit vector pointing along compass bearing `deg`.
    pub fn unit(deg: f64) -> Xy {
        let (s, c) = deg.to_radians().sin_cos();
        Xy::new(s, c)
    }
    /// Compass bearing of this vector, degrees in [0, 360).
    pub fn bearing(self) -> f64 {
        wrap360(self.e.atan2(self.n).to_degrees())
    }
}

/// A local east/north frame around an origin: the azimuthal equidistant projection built on the
/// geodesic, so distances and bearings from the origin are exact and the distortion within the few
/// kilometres of a pattern is negligible.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LocalFrame {
    /// The frame's origin.
    pub origin: GeoPoint,
}

impl LocalFrame {
    /// A frame around `origin`.
    pub const fn new(origin: GeoPoint) -> Self {
        Self { origin }
    }
    /// Projects a geodetic point into the frame.
    pub fn to_local(&self, p: GeoPoint) -> Xy {
        let inv = inverse(self.origin, p);
        Xy::unit(inv.azi1).scale(inv.distance)
    }
    /// Converts a local point back to geodetic coordinates.
    pub fn to_geo(&self, xy: Xy) -> GeoPoint {
        let d = xy.norm();
        if d == 0.0 {
            return self.origin;
        }
        direct(self.origin, xy.bearing(), d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn known_distance_flinders_peak_buninyong() {
        // Vincenty's own test case (Flinders Peak to Buninyong): 54 972.271 m, azimuth 306°52'05.37".
        let p1 = GeoPoint::new(
            -(37.0 + 57.0 / 60.0 + 3.72030 / 3600.0),
            144.0 + 25.0 / 60.0 + 29.52440 / 3600.0,
        );
        let p2 = GeoPoint::new(
            -(37.0 + 39.0 / 60.0 + 10.15610 / 3600.0),
            143.0 + 55.0 / 60.0 + 35.38390 / 3600.0,
        );
        let inv = inverse(p1, p2);
        assert!(
            (inv.distance - 54_972.271).abs() < 0.001,
            "{}",
            inv.distance
        );
        let azi = 306.0 + 52.0 / 60.0 + 5.37 / 3600.0;
        assert!((inv.azi1 - azi).abs() < 1e-4, "{}", inv.azi1);
    }

    #[test]
    fn one_degree_of_latitude_at_equator() {
        let d = distance(GeoPoint::new(0.0, 0.0), GeoPoint::new(1.0, 0.0));
        assert!((d - 110_574.389).abs() < 0.01, "{d}");
    }

    #[test]
    fn antipodal_falls_back_without_panicking() {
        let inv = inverse(GeoPoint::new(0.0, 0.0), GeoPoint::new(0.5, 179.7));
        assert!(inv.distance > 19_000_000.0);
    }

    proptest! {
        #[test]
        fn direct_then_inverse_round_trips(
            lat in -80.0f64..80.0, lon in -179.0f64..179.0,
            azi in 0.0f64..360.0, dist in 0.5f64..200_000.0,
        ) {
            let p = GeoPoint::new(lat, lon);
            let q = direct(p, azi, dist);
            let inv = inverse(p, q);
            prop_assert!((inv.distance - dist).abs() < 1e-4, "{} vs {}", inv.distance, dist);
            prop_assert!(wrap180(inv.azi1 - azi).abs() < 1e-6, "{} vs {}", inv.azi1, azi);
        }

        #[test]
        fn local_frame_round_trips(e in -5000.0f64..5000.0, n in -5000.0f64..5000.0) {
            let f = LocalFrame::new(GeoPoint::new(41.275, 1.987));
            let back = f.to_local(f.to_geo(Xy::new(e, n)));
            prop_assert!((back.e - e).abs() < 1e-5 && (back.n - n).abs() < 1e-5);
        }
    }
}

//! Where the team's local NED frame sits on the Earth, and the conversion between NED positions
//! and latitude, longitude and altitude: the flat-Earth (equirectangular) approximation about
//! the origin, on the WGS-84 equatorial sphere. Every conversion in cooploc (SIM_STATE and
//! GPS_INPUT on the wire, Foxglove's map, the MAVProxy module's map) uses these.

use nalgebra::Vector3;

/// Equatorial radius of WGS-84, m: the sphere of the flat-Earth approximation below.
pub const EARTH_RADIUS_M: f64 = 6_378_137.0;

/// Where the origin of the local NED frame sits on the Earth. The simulated world is a flat
/// tangent plane; positions go on the wire as latitude and longitude by the flat-Earth
/// (equirectangular) approximation about this point, which is exact to well under a centimetre
/// over the few kilometres of a scenario (the error grows as distance^2 / R).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeoOrigin {
    pub lat_deg: f64,
    pub lon_deg: f64,
    /// Altitude of the NED origin (D = 0), m above the reference.
    pub alt_m: f64,
}

/// A geodetic position: degrees and metres (altitude up).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geodetic {
    pub lat_deg: f64,
    pub lon_deg: f64,
    pub alt_m: f64,
}

/// Local NED (m) to latitude, longitude (wrapped to [-180, 180)) and altitude.
pub fn ned_to_geodetic(origin: &GeoOrigin, pos_ned_m: &Vector3<f64>) -> Geodetic {
    let lat_deg = origin.lat_deg + (pos_ned_m[0] / EARTH_RADIUS_M).to_degrees();
    let lon_deg = origin.lon_deg + (pos_ned_m[1] / (EARTH_RADIUS_M * origin.lat_deg.to_radians().cos())).to_degrees();
    Geodetic { lat_deg, lon_deg: wrap_lon_deg(lon_deg), alt_m: origin.alt_m - pos_ned_m[2] }
}

/// Inverse of [`ned_to_geodetic`] (the longitude difference is taken the short way round).
pub fn geodetic_to_ned(origin: &GeoOrigin, g: &Geodetic) -> Vector3<f64> {
    let dlon = wrap_lon_deg(g.lon_deg - origin.lon_deg);
    Vector3::new(
        (g.lat_deg - origin.lat_deg).to_radians() * EARTH_RADIUS_M,
        dlon.to_radians() * EARTH_RADIUS_M * origin.lat_deg.to_radians().cos(),
        origin.alt_m - g.alt_m,
    )
}

/// `lon` in [-180, 180): as it is when it is there already (adding and taking 180 back would
/// cost a few nanometres of precision), else wrapped.
fn wrap_lon_deg(lon: f64) -> f64 {
    if (-180.0..180.0).contains(&lon) { lon } else { (lon + 180.0).rem_euclid(360.0) - 180.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ned_round_trips_through_geodetic_and_the_longitude_wraps() {
        let origin = GeoOrigin { lat_deg: 34.7, lon_deg: 179.999, alt_m: 12.0 };
        let p = Vector3::new(1234.5, 987.25, -3.5);
        let g = ned_to_geodetic(&origin, &p);
        assert!(g.lon_deg < -179.9, "east of the antimeridian: {}", g.lon_deg);
        assert!((geodetic_to_ned(&origin, &g) - p).norm() < 1e-6);
        assert_eq!(g.alt_m, 15.5);
    }
}

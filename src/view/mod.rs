//! One view of the team for every display: what the ground station's web page, its live
//! Foxglove channels, the Foxglove channels of an MCAP log and the MAVProxy module
//! (`tools/mavproxy/`) show is built here, so that they agree by construction.
//!
//! - **Names and colours**: [`vehicle_name`], and one palette by platform id ([`PALETTE`],
//!   [`vehicle_rgb`], [`vehicle_hex`]). The page takes each vehicle's colour from the JSON
//!   ([`VehicleStyle`]), the Foxglove messages from [`foxglove::vehicle_color`], the MAVProxy
//!   module from the same ten colours written out.
//! - **Frames**: positions in the team's local NED frame, as the filters keep them. Foxglove
//!   sees them in frame `ned` under its display frame `world` (ENU) through one fixed
//!   transform, and on its map as latitude/longitude about the team's origin (flat Earth,
//!   [`crate::protocol::wire::ned_to_geodetic`]); the page draws N up, E right.
//! - **Ellipses and consistency**: the 95 % horizontal ellipse, its chi-square constant and the
//!   position NEES of [`crate::estimation::consistency`], nowhere else.
//! - **Health** ([`health`]): disagreements and their healing seen from the nodes' epoch
//!   reports, each node's estimate rate, its bytes per second against the link budget, and
//!   whether its frames are signed.
//!
//! [`foxglove`] turns estimates, truth and health into Foxglove's well-known messages; the
//! live server ([`crate::gcs::foxglove_live`]) and the recorder ([`crate::recording`]) both
//! publish what it returns on the same topics ([`crate::recording::topics`]).

pub mod foxglove;
pub mod health;

use serde::Serialize;

use crate::estimation::PlatformId;

/// Vehicle colours (Tableau 10), by platform id: vehicle 1 takes the first.
pub const PALETTE: [[u8; 3]; 10] = [
    [0x1f, 0x77, 0xb4],
    [0xff, 0x7f, 0x0e],
    [0x2c, 0xa0, 0x2c],
    [0xd6, 0x27, 0x28],
    [0x94, 0x67, 0xbd],
    [0x8c, 0x56, 0x4b],
    [0xe3, 0x77, 0xc2],
    [0x7f, 0x7f, 0x7f],
    [0xbc, 0xbd, 0x22],
    [0x17, 0xbe, 0xcf],
];

/// The colour of vehicle `id` (platform 0, never a vehicle, takes the last).
pub fn vehicle_rgb(id: PlatformId) -> [u8; 3] {
    PALETTE[(usize::from(id) + PALETTE.len() - 1) % PALETTE.len()]
}

/// The colour of vehicle `id` as CSS (`#rrggbb`).
pub fn vehicle_hex(id: PlatformId) -> String {
    let [r, g, b] = vehicle_rgb(id);
    format!("#{r:02x}{g:02x}{b:02x}")
}

/// What every display calls vehicle `id`.
pub fn vehicle_name(id: PlatformId) -> String {
    format!("vehicle {id}")
}

/// A vehicle's name and colour, as the page receives them.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct VehicleStyle {
    pub name: String,
    /// `#rrggbb`.
    pub color: String,
}

impl VehicleStyle {
    pub fn of(id: PlatformId) -> Self {
        VehicleStyle { name: vehicle_name(id), color: vehicle_hex(id) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vehicle_one_is_blue_and_the_palette_wraps() {
        assert_eq!(vehicle_hex(1), "#1f77b4");
        assert_eq!(vehicle_hex(2), "#ff7f0e");
        assert_eq!(vehicle_hex(11), vehicle_hex(1));
        assert_eq!(vehicle_hex(0), "#17becf");
        assert_eq!(VehicleStyle::of(3), VehicleStyle { name: "vehicle 3".into(), color: "#2ca02c".into() });
    }
}

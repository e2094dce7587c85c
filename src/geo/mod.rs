//! Geodesy for georeferencing: WGS84 geodetic ↔ Earth-centred Earth-fixed coordinates and the
//! output map projection (an EPSG code, or the UTM zone of the first fix), through the `proj4rs`
//! crate (a Rust transcription of PROJ's projections) rather than hand-written projections.
//!
//! Units: latitude and longitude in degrees at this module's surface, heights and projected
//! coordinates in metres (the CRS's units).

pub mod crs;
pub mod dem;
/// Direct georeferencing of one pulse (pose, scan angles, lever arm, boresight → geometry).
pub mod direct_georeference;
/// A local quadratic model of the map projection (`[georeference] projection = "per_span"`).
pub mod local_projection;
/// The source wrapper that georeferences a pulse stream from its navigation stream.
pub use crs::{GeoError, OutputCrs, ecef_of, geodetic_of_ecef, utm_epsg};

//! Points <-> range images. Owns the decoded scan ([`Scan`]), sensor profiles
//! ([`SensorProfile`]: beam elevations, columns, valid range), the projection of a
//! scan onto a profile's angle grid ([`project`]), the way back to points, and
//! resampling of angle grids. No I/O beyond reading dataset files, no MCAP, no burn.

pub mod kitti;
pub mod profile;
pub mod projection;
pub mod range_image;
pub mod scan;

pub use profile::SensorProfile;
pub use projection::{ProjectionError, Strategy, project};
pub use range_image::{AngleGrid, RangeImage};
pub use scan::Scan;

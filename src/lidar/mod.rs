//! Points <-> range images. Owns the decoded scan ([`Scan`]), sensor profiles
//! ([`SensorProfile`]: beam elevations, columns, valid range) and their estimation
//! from data ([`estimate`]), the projection of a scan onto a profile's angle grid
//! ([`project`]), the way back to points, and resampling of angle grids and range
//! images ([`resample`]). Readers for dataset files on disk (KITTI, nuScenes, PCD, Ouster
//! PCAP captures) live here too, and a recording's own ray-drop rates ([`drop_census`]); MCAP is left to
//! `io`, models to later modules.

pub mod drop_census;
pub mod edges;
pub mod estimate;
pub mod holes;
pub mod kitti;
pub mod kitti_boxes;
pub mod line_fill;
pub mod nuscenes;
pub mod ouster_pcap;
pub mod pcd;
pub mod profile;
pub mod projection;
pub mod range_image;
pub mod resample;
pub mod scan;
pub mod scatter;
pub mod surface;
pub mod sweep;

pub use estimate::{EstimateMethod, SensorEstimate, estimate_profile};
pub use profile::SensorProfile;
pub use projection::{ProjectionError, Strategy, project};
pub use range_image::{AngleGrid, RangeImage};
pub use resample::{Interpolation, resample_by_surface, resample_image, resample_to_profile};
pub use scan::Scan;
pub use scatter::{ScatterFill, fill_scattered, fill_scattered_in_angle, fill_scattered_where};
pub use surface::{Guide, SurfaceRule};

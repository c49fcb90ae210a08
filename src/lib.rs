//! rangegan-mcap: LiDAR range images and a range-image GAN for MCAP recordings.
//!
//! One scan's path through the crate:
//!
//! 1. [`io`] streams records out of an MCAP file and decodes point-cloud messages
//!    (ROS 1/ROS 2 `PointCloud2`, `foxglove.PointCloud`) into a [`lidar::Scan`];
//! 2. [`lidar`] projects the scan onto a sensor's angle grid, giving a
//!    [`lidar::RangeImage`] (and back to points, or resampled to another grid);
//! 3. later stages (the GAN model, auto-decoding, physics) work on range images;
//! 4. [`io`] encodes the results as new channels and writes them beside every
//!    copied input record, atomically.
//!
//! Beside that path, [`diagnose`] compares a simulated with a real recording and fits the
//! physics the simulator left out, and [`segment`] measures what rendered ray drop is worth
//! downstream: a segmentation network trained on simulated scans, scored on real ones.

pub mod cli;
pub mod dataset;
pub mod decode;
pub mod diagnose;
pub mod error;
pub mod io;
pub mod lidar;
pub mod model;
pub mod physics;
pub mod pipeline;
pub mod recording;
pub mod report;
pub mod segment;
pub mod sim;
pub mod train;
pub mod util;

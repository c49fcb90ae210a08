//! Training, kept apart from inference: everything here produces weights that the inference
//! modules ([`crate::model`], [`crate::decode`], [`crate::segment`]) load.
//!
//! - [`run_dir`]: what every run directory shares: the backend, the atomic checkpoint swap.
//! - [`config`]: a GAN run's saved settings, options and checkpointed state.
//! - [`gan`]: the range-image GAN's training loop, with checkpoints and resume.
//! - [`update`]: gradient means and masks, the generator's EMA, adaptive augmentation.
//! - [`regularise`]: the discriminator's other regularisers for small data: LeCam,
//!   DiffAugment-style translation and cutout, adaptive pseudo augmentation.
//! - [`encoder`]: the amortised encoder of `convert --quality fast`, trained against a
//!   frozen generator (`train-encoder`).
//! - [`growth`]: coarse-to-fine training: the generator's synthesis pyramid grown a level at
//!   a time, each level with its own discriminator, on real scans sampled at that level.
//! - [`reconstruct`]: reconstruction-assisted training: an encoder in the generator's loop.
//! - [`widen`]: function-preserving widening of a trained generator, to go on training
//!   a run at a larger width.
//! - [`row_fill`]: the learned correction of restored rows ([`crate::decode::row_fill`]).
//! - [`hole_fill`]: the learned correction of dropped rays ([`crate::decode::hole_fill`]).
//! - [`ray_move`]: fitting either correction.
//! - [`scans`]: where the training scans come from (KITTI folders or MCAP recordings of
//!   any sensor) and the validation split.

pub mod config;
pub mod encoder;
pub mod gan;
pub mod growth;
pub mod hole_fill;
pub mod ray_move;
pub mod reconstruct;
pub mod regularise;
pub mod row_fill;
pub mod run_dir;
pub mod scans;
pub mod spatial;
pub mod update;
pub mod widen;

pub use config::*;
pub use gan::*;
pub use run_dir::*;

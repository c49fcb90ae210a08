//! Sim2Real diagnosis: given a simulated and an unpaired real recording (both
//! projected onto one range-image grid), name the catalogue effects
//! ([`crate::physics`]) the simulator left out, fit them, and show the held-out
//! fit improve. This module uses the effects catalogue; the catalogue knows
//! nothing of it.
//!
//! The pipeline, one file per step:
//!
//! ```text
//! range images ──► completion ──► features ──► stats ──────────────► report
//!  (sim, real)     (dropped        (range,      where drop rates       (effects,
//!                   rays get a      incidence,   diverge: z-tests,      fit before/
//!                   range: GAN      edges,       Benjamini-Hochberg     after, curves,
//!                   x_d or          class)                              maps, fitted
//!                   neighbours)          │                              physics)
//!                                        ├──► fit + drop ───────────────►│
//!                                        │    which drop effect: joint    │
//!                                        │    keep model, forward         │
//!                                        │    selection on held-out scans │
//!                                        └──► residual ──────────────────►┘
//!                                             which effect moves returns:
//!                                             local range statistics
//! ```
//!
//! - [`completion`]: the neighbour fill or the GAN's completed depth x_d.
//! - [`features`]: per-pixel features of one scan ([`features::ScanFeatures`]).
//! - [`gaps`]: sectors of a scan without any return, gaps in the recording left out.
//! - [`stats`]: conditional drop rates and their significance (*where*).
//! - [`fit`]: the joint drop model and the forward selection (*which*).
//! - [`drop`]: the drop candidates, one [`fit::DropFamily`] each.
//! - [`residual`]: the range-residual candidates.
//! - [`real_scan`]: a real scan as a simulated one, for effects applied to real data.
//! - [`report`]: the whole diagnosis and the numbers the report shows; writing
//!   the files is [`crate::report`]'s job.

pub mod completion;
pub mod drop;
pub mod features;
pub mod fit;
pub mod gaps;
pub mod real_scan;
pub mod report;
pub mod residual;
pub mod stats;
#[cfg(test)]
mod tests;

pub use report::{DiagnoseError, DiagnoseOptions, Diagnosis, diagnose};

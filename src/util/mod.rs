//! Code without domain knowledge that the rest of the crate shares.
//!
//! - [`adam`]: the Adam optimiser over host-side weights.
//! - [`bounds`]: checks that sizes read from files and flags lie in a sane range, before
//!   anything is allocated from them.
//! - [`fs`]: atomic file writes.
//! - [`json`]: merging a saved JSON config over the current defaults.
//! - [`math`]: scalar functions (a stable softplus).
//! - [`matmul`]: single-threaded matrix products on host slices.
//! - [`mlp`]: a small fully connected network with its own backward pass and Adam.
//! - [`png`]: PNG encoding.
//! - [`rng`]: deterministic random numbers, keyed or sequential.
//! - [`tensor`]: host vectors <-> burn tensors.

pub mod adam;
pub mod bounds;
pub mod fs;
pub mod init;
pub mod json;
pub mod math;
pub mod matmul;
pub mod mlp;
pub mod png;
pub mod pools;
pub mod rng;
pub mod tensor;
pub mod time;

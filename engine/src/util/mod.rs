//! What every stage leans on and none owns: rays, boxes and floating-point error bounds,
//! sampling and hashing of sample keys, and content fingerprints.

pub mod color;
pub mod fingerprint;
pub mod math;
pub mod sampling;
pub mod stats;
#[cfg(test)]
pub(crate) mod test_random;

//! Stable hashes of values: FNV-1a over their little-endian bytes in a fixed order, the
//! same on every machine and run, for checkpoints, caches and tree comparisons.

/// FNV-1a over values fed in a fixed order, each as its little-endian bytes: a
/// fingerprint that does not change with formatting or platform.
#[derive(Clone, Copy, Debug)]
pub struct Fingerprint(u64);

impl Fingerprint {
    /// A hash started with a tag naming what is hashed (and its layout's version).
    pub fn new(tag: &str) -> Self {
        let mut hash = Self::untagged();
        hash.text(tag);
        hash
    }

    /// A hash with nothing fed yet (FNV-1a's offset basis).
    pub fn untagged() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }

    /// Adds bytes.
    pub fn bytes(&mut self, bytes: &[u8]) -> &mut Self {
        for &b in bytes {
            self.0 = (self.0 ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
        }
        self
    }

    /// Adds a string and its length (so "ab" + "c" differs from "a" + "bc").
    pub fn text(&mut self, text: &str) -> &mut Self {
        self.u64(text.len() as u64).bytes(text.as_bytes())
    }

    /// Adds a `u32`.
    pub fn u32(&mut self, value: u32) -> &mut Self {
        self.bytes(&value.to_le_bytes())
    }

    /// Adds a `u64`.
    pub fn u64(&mut self, value: u64) -> &mut Self {
        self.bytes(&value.to_le_bytes())
    }

    /// Adds an `f32` by its bits.
    pub fn f32(&mut self, value: f32) -> &mut Self {
        self.u32(value.to_bits())
    }

    /// The hash.
    pub fn finish(&self) -> u64 {
        self.0
    }
}

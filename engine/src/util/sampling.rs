//! Stateless random numbers and sample warps. A sample's value is a hash of (seed, pixel,
//! frame, sample, dimension), so images never depend on tile order or thread count.

use glam::{Vec2, Vec3A};

/// SplitMix64's finaliser: a bijective 64-bit mix.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// A small sequential generator (SplitMix64) for scene generation and tests; rendering
/// uses the stateless [`SampleKey`] instead.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SplitMix64(pub u64);

impl SplitMix64 {
    /// Next 64 random bits.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        mix64(self.0)
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in [lo, hi).
    #[inline]
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f32()
    }
}

/// The random stream of one sample of one pixel in one frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SampleKey {
    key: u64,
}

impl SampleKey {
    /// The stream for `(seed, pixel, frame, sample)`.
    #[inline]
    pub fn new(seed: u64, x: u32, y: u32, frame: u32, sample: u32) -> Self {
        let mut h = mix64(seed ^ 0x9e37_79b9_7f4a_7c15);
        h = mix64(h ^ ((x as u64) << 32 | y as u64));
        h = mix64(h ^ ((frame as u64) << 32 | sample as u64));
        Self { key: h }
    }

    /// A uniform number in [0, 1) for dimension `dim`.
    #[inline]
    pub fn get(&self, dim: u32) -> f32 {
        let h = mix64(
            self.key
                .wrapping_add((dim as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15)),
        );
        (h >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }

    /// Two numbers, dimensions `dim` and `dim + 1`.
    #[inline]
    pub fn get2(&self, dim: u32) -> Vec2 {
        Vec2::new(self.get(dim), self.get(dim + 1))
    }
}

/// Maps the unit square to the unit disk, preserving stratification (Shirley–Chiu).
#[inline]
pub fn concentric_disk(u: Vec2) -> Vec2 {
    let o = 2.0 * u - Vec2::ONE;
    if o == Vec2::ZERO {
        return Vec2::ZERO;
    }
    let (r, theta) = if o.x.abs() > o.y.abs() {
        (o.x, std::f32::consts::FRAC_PI_4 * (o.y / o.x))
    } else {
        (
            o.y,
            std::f32::consts::FRAC_PI_2 - std::f32::consts::FRAC_PI_4 * (o.x / o.y),
        )
    };
    r * Vec2::new(theta.cos(), theta.sin())
}

/// A cosine-distributed direction around +Z (pdf = cos θ / π).
#[inline]
pub fn cosine_hemisphere(u: Vec2) -> Vec3A {
    let d = concentric_disk(u);
    Vec3A::new(d.x, d.y, (1.0 - d.length_squared()).max(0.0).sqrt())
}

/// An orthonormal basis `(t, b)` completing unit `n` (Duff et al. 2017).
#[inline]
pub fn orthonormal_basis(n: Vec3A) -> (Vec3A, Vec3A) {
    let sign = 1.0f32.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (
        Vec3A::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
        Vec3A::new(b, sign + n.y * n.y * a, -n.y),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_mean_and_range() {
        let mut sum = 0.0f64;
        let n = 100_000;
        for i in 0..n {
            let v = SampleKey::new(7, i % 317, i / 317, 3, 1).get(5);
            assert!((0.0..1.0).contains(&v));
            sum += v as f64;
        }
        let mean = sum / n as f64;
        // Standard error of the mean of U(0,1) over 1e5 draws is ~9e-4.
        assert!((mean - 0.5).abs() < 5e-3, "mean {mean}");
    }

    #[test]
    fn keys_differ_by_every_field() {
        let base = SampleKey::new(1, 2, 3, 4, 5).get(0);
        for other in [
            SampleKey::new(9, 2, 3, 4, 5),
            SampleKey::new(1, 9, 3, 4, 5),
            SampleKey::new(1, 2, 9, 4, 5),
            SampleKey::new(1, 2, 3, 9, 5),
            SampleKey::new(1, 2, 3, 4, 9),
        ] {
            assert_ne!(other.get(0), base);
        }
    }

    #[test]
    fn basis_is_orthonormal() {
        for i in 0..1000 {
            let k = SampleKey::new(0, i, 0, 0, 0);
            let n = (Vec3A::new(k.get(0), k.get(1), k.get(2)) * 2.0 - Vec3A::ONE)
                .normalize_or(Vec3A::Z);
            let (t, b) = orthonormal_basis(n);
            assert!(t.dot(n).abs() < 1e-5 && b.dot(n).abs() < 1e-5 && t.dot(b).abs() < 1e-5);
            assert!((t.length() - 1.0).abs() < 1e-5 && (b.length() - 1.0).abs() < 1e-5);
        }
    }
}

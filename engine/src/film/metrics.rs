//! Image error metrics against a reference: what the convergence harness and
//! `sylva compare` report.

use glam::Vec3;

/// The error of an image against a reference of the same size.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ImageError {
    /// Root mean squared error over pixels and channels.
    pub rmse: f64,
    /// Relative MSE: mean over pixels and channels of (I − R)² / (R² + 0.01).
    pub relmse: f64,
}

/// Errors of `image` against `reference` (row-major linear RGB); `None` when the sizes
/// differ or the images are empty. Non-finite pixels count as infinitely wrong.
pub fn image_error(reference: &[Vec3], image: &[Vec3]) -> Option<ImageError> {
    if reference.len() != image.len() || reference.is_empty() {
        return None;
    }
    let (mut squared, mut relative) = (0f64, 0f64);
    for (r, i) in reference.iter().zip(image) {
        for c in 0..3 {
            let (r, i) = (r[c] as f64, i[c] as f64);
            let d2 = (i - r) * (i - r);
            squared += d2;
            relative += d2 / (r * r + 0.01);
        }
    }
    let n = (reference.len() * 3) as f64;
    let nan_to_infinity = |v: f64| if v.is_nan() { f64::INFINITY } else { v };
    Some(ImageError {
        rmse: nan_to_infinity((squared / n).sqrt()),
        relmse: nan_to_infinity(relative / n),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_match_their_definitions() {
        let reference = vec![Vec3::new(1.0, 0.0, 0.5), Vec3::ZERO];
        let image = vec![Vec3::new(1.0, 0.3, 0.5), Vec3::new(0.0, 0.0, 0.1)];
        let e = image_error(&reference, &image).unwrap();
        assert!((e.rmse - ((0.09 + 0.01) / 6.0f64).sqrt()).abs() < 1e-7);
        assert!((e.relmse - (0.09 / 0.01 + 0.01 / 0.01) / 6.0).abs() < 1e-5);
        assert_eq!(
            image_error(&reference, &reference).unwrap(),
            ImageError::default()
        );
        assert!(image_error(&reference, &image[..1]).is_none());
        let bad = vec![Vec3::NAN, Vec3::ZERO];
        assert_eq!(image_error(&reference, &bad).unwrap().rmse, f64::INFINITY);
    }
}

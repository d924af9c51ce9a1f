//! The watertight ray–triangle test on raw float bits: a hit always has a finite t in
//! (0, t_max) and finite barycentrics that sum to 1; nothing panics.
#![no_main]
use glam::Vec3A;
use libfuzzer_sys::fuzz_target;
use sylva_engine::math::Ray;
use sylva_engine::triangle::WatertightRay;

fuzz_target!(|data: [u32; 16]| {
    let f: Vec<f32> = data.iter().map(|&b| f32::from_bits(b)).collect();
    let v = |i: usize| Vec3A::new(f[i], f[i + 1], f[i + 2]);
    let ray = Ray::segment(v(0), v(3), f[15]);
    if let Some(hit) = WatertightRay::new(&ray).intersect(v(6), v(9), v(12), ray.t_max) {
        assert!(hit.t.is_finite() && hit.t > 0.0 && hit.t < ray.t_max, "{hit:?}");
        assert!(hit.barycentrics.is_finite(), "{hit:?}");
        assert!((hit.barycentrics.element_sum() - 1.0).abs() < 1e-3, "{hit:?}");
    }
});

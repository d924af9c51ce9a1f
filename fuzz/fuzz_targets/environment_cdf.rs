//! Environment-map CDF construction: any small map of arbitrary f32 texels (NaN, ∞ and
//! negatives included) gives virtual lights whose power equals the repaired map's
//! integral and whose sampling always returns a light with positive probability.
#![no_main]
use glam::Vec3;
use libfuzzer_sys::fuzz_target;
use sylva_engine::environment::{EnvironmentMap, VirtualLights};

fuzz_target!(|data: &[u8]| {
    if data.len() < 4 {
        return;
    }
    let width = u32::from(data[0] % 32) + 1;
    let height = u32::from(data[1] % 16) + 1;
    let count = usize::from(u16::from_le_bytes([data[2], data[3]]) % 600) + 1;
    let floats: Vec<f32> = data[4..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let texels: Vec<Vec3> = (0..(width * height) as usize)
        .map(|i| {
            let f = |k: usize| floats.get(3 * i + k).copied().unwrap_or(0.0);
            Vec3::new(f(0), f(1), f(2))
        })
        .collect();
    let Ok((map, _repaired)) = EnvironmentMap::new(width, height, texels) else {
        return;
    };
    let lights = VirtualLights::median_cut(&map, count);
    let (power, integral) = (lights.total_irradiance(), map.integral());
    if integral.is_finite() && power.is_finite() {
        let scale = integral.abs().max_element().max(1e-30);
        assert!(((power - integral).abs().max_element() / scale) < 1e-3, "{power} vs {integral}");
    }
    for u in [0.0, 0.3, 0.999_999_9] {
        if let Some(light) = lights.sample(u) {
            assert!(light.probability > 0.0 && light.direction.is_finite());
        }
    }
});

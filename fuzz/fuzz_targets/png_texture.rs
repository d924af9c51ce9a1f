//! Texture decoding (PNG/JPEG) of arbitrary bytes: an error, or a texture whose samples
//! are finite at any UV, including huge and non-finite ones.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(texture) = sylva_scenes::gltf::decode_texture(data) {
        for uv in [
            glam::Vec2::ZERO,
            glam::Vec2::new(0.5, 0.25),
            glam::Vec2::new(-3.7, 1e9),
            glam::Vec2::new(f32::NAN, f32::INFINITY),
        ] {
            assert!(texture.sample(uv).is_finite());
        }
        assert!(texture.mean_opaque_color().is_finite());
    }
});

//! glTF/GLB import of arbitrary bytes: an error or a scene, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = std::path::Path::new("/nonexistent/fuzz.glb");
    if let Ok(scene) = sylva_scenes::gltf::import_slice(data, path) {
        let model = scene.bake();
        assert!(model.mesh.positions.iter().all(|p| p.is_finite()));
    }
});

//! glTF/GLB import of arbitrary bytes: an error or a scene, never a panic that escapes.
//!
//! The importer turns panics inside the gltf crate into errors with `catch_unwind`;
//! libfuzzer-sys's panic hook would abort on those before they are caught, so the target
//! installs a hook that only prints. A panic that escapes the importer still aborts (the
//! fuzz harness's own `catch_unwind` sees it) and is reported as a crash.
#![no_main]
use libfuzzer_sys::fuzz_target;

static QUIET_HOOK: std::sync::Once = std::sync::Once::new();

fuzz_target!(|data: &[u8]| {
    QUIET_HOOK.call_once(|| {
        std::panic::set_hook(Box::new(|info| eprintln!("panic (caught or not): {info}")));
    });
    let path = std::path::Path::new("/nonexistent/fuzz.glb");
    if let Ok(scene) = sylva_scenes::gltf::import_slice(data, path) {
        let model = scene.bake();
        assert!(model.mesh.positions.iter().all(|p| p.is_finite()));
    }
});

//! `.hdr` / `.exr` environment maps from arbitrary bytes: an error naming the file, or a
//! map whose texels are all finite and non-negative.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, bytes)) = data.split_first() else {
        return;
    };
    let extension = if kind % 2 == 0 { "hdr" } else { "exr" };
    let path = std::env::temp_dir().join(format!("sylva-fuzz-{}.{extension}", std::process::id()));
    std::fs::write(&path, bytes).unwrap();
    match sylva_scenes::environment::load_environment(&path) {
        Ok(loaded) => {
            let map = loaded.map;
            for y in 0..map.height() {
                for x in 0..map.width() {
                    let t = map.texel(x, y);
                    assert!(t.is_finite() && t.min_element() >= 0.0);
                }
            }
        }
        Err(e) => assert!(e.to_string().contains("sylva-fuzz")),
    }
});

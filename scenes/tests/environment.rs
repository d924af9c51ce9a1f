//! Environment maps from real files: the direction ↔ texel mapping against OpenEXR's
//! labelled orientation map, real HDR maps, and broken files.
// Without the `exr` feature only the Radiance tests run, and some imports go unused.
#![cfg_attr(not(feature = "exr"), allow(unused_imports))]

use glam::Vec3;
use std::path::{Path, PathBuf};
use sylva_engine::environment::{VirtualLights, direction_to_uv, uv_to_direction};
use sylva_scenes::environment::load_environment;

fn asset(relative: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data")
        .join(relative)
}

#[cfg(feature = "exr")]
#[test]
fn the_mapping_matches_the_labelled_orientation_map() {
    // Each of the map's four horizon views (+X, +Z, −X, −Z) has an axis gizmo: a
    // vertical line at the view's centre and a horizontal arm along the positive
    // horizontal axis across the view. Looking along f with +Y up, screen-right is
    // f × Y, so the arm goes right exactly when (f × Y) · axis > 0.
    let map = load_environment(&asset("hdr/exr/OrientationLatLong.exr"))
        .unwrap()
        .map;
    let (w, h) = (map.width() as i64, map.height() as i64);
    let ink = |x: i64, y: i64| {
        map.texel(x.rem_euclid(w) as u32, y.clamp(0, h - 1) as u32)
            .max_element()
            < 0.5
    };
    for (forward, axis) in [
        (Vec3::X, Vec3::Z),
        (Vec3::Z, Vec3::X),
        (-Vec3::X, Vec3::Z),
        (-Vec3::Z, Vec3::X),
    ] {
        let (u, v) = direction_to_uv(forward);
        let (cx, cy) = ((u * w as f32).round() as i64, (v * h as f32).round() as i64);
        let vertical = (cy - 50..cy - 6).filter(|&y| ink(cx, y)).count();
        assert!(vertical > 40, "{forward}: no gizmo at column {cx}");
        let right = (cx + 6..cx + 50).filter(|&x| ink(x, cy)).count();
        let left = (cx - 50..cx - 6).filter(|&x| ink(x, cy)).count();
        let expected_right = forward.cross(Vec3::Y).dot(axis) > 0.0;
        assert_eq!(
            right > left,
            expected_right,
            "{forward}: arm right {right}, left {left}"
        );
        // And moving right in the image turns the view towards f × Y.
        let turned = uv_to_direction(u + 0.01, v);
        assert!((turned - forward).dot(forward.cross(Vec3::Y)) > 0.0);
    }
    // The zenith row is the top of the image.
    assert!((uv_to_direction(0.3, 0.0) - Vec3::Y).length() < 1e-5);
}

#[test]
fn real_hdr_maps_load_and_keep_their_power_in_the_virtual_lights() {
    for name in ["noon_grass_1k.hdr", "kloofendal_overcast_1k.hdr"] {
        let loaded = load_environment(&asset(&format!("hdr/{name}"))).unwrap();
        assert_eq!((loaded.map.width(), loaded.map.height()), (1024, 512));
        assert_eq!(loaded.repaired_texels, 0, "{name}");
        let integral = loaded.map.integral();
        assert!(integral.min_element() > 0.0, "{name}");
        let lights = VirtualLights::median_cut(&loaded.map, 1024);
        let total = lights.total_irradiance();
        assert!(
            ((total - integral) / integral).abs().max_element() < 1e-4,
            "{name}: {total} vs {integral}"
        );
    }
}

#[test]
fn the_noon_sun_is_captured_near_the_zenith() {
    // noon_grass has its sun near the zenith: the brightest virtual light points up.
    let loaded = load_environment(&asset("hdr/noon_grass_1k.hdr")).unwrap();
    let lights = VirtualLights::median_cut(&loaded.map, 256);
    let brightest = lights
        .lights()
        .iter()
        .max_by(|a, b| a.probability.total_cmp(&b.probability))
        .unwrap();
    assert!(brightest.direction.y > 0.7, "{brightest:?}");
}

#[test]
fn broken_maps_are_errors_naming_the_file() {
    let dir = std::env::temp_dir().join(format!("sylva-env-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cases = [
        (
            "truncated.hdr",
            b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 512 +X 1024\n\x02\x02".to_vec(),
        ),
        ("empty.exr", Vec::new()),
        ("map.png", b"\x89PNG".to_vec()),
        (
            "huge.hdr",
            b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 100000 +X 100000\n".to_vec(),
        ),
    ];
    for (file, bytes) in cases {
        let path = dir.join(file);
        std::fs::write(&path, bytes).unwrap();
        let e = load_environment(&path).unwrap_err().to_string();
        assert!(e.contains(file), "{file}: {e}");
    }
    let e = load_environment(&dir.join("huge.hdr"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("100000x100000"), "{e}");
}

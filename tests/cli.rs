//! End-to-end tests of the `sylva` binary: real images out, same bits for any thread
//! count, clear errors for bad arguments.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn sylva(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sylva"))
        .args(args)
        .output()
        .expect("the binary runs")
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sylva-cli-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

const EXR_WIDTH: usize = 64;

fn read_exr(path: &Path) -> Vec<[f32; 4]> {
    let image = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |size, _| vec![[0f32; 4]; size.width() * size.height()],
        |pixels: &mut Vec<[f32; 4]>, pos, (r, g, b, a): (f32, f32, f32, f32)| {
            pixels[pos.y() * EXR_WIDTH + pos.x()] = [r, g, b, a]
        },
    )
    .unwrap();
    image.layer_data.channel_data.pixels
}

#[test]
fn renders_png_with_real_content() {
    let dir = temp_dir("png");
    let out = dir.join("meadow.png");
    let run = sylva(&[
        "render",
        "--width",
        "64",
        "--height",
        "48",
        "--spp",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        run.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&run.stderr)
    );
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        stdout.contains("rays/s") && stdout.contains("instances"),
        "summary line missing: {stdout}"
    );
    let png = image::open(&out).unwrap().to_rgb8();
    assert_eq!(png.dimensions(), (64, 48));
    let first = png.get_pixel(0, 0);
    let distinct: std::collections::HashSet<_> = png.pixels().map(|p| p.0).collect();
    assert!(
        png.pixels().any(|p| p != first) && distinct.len() > 50,
        "image is (nearly) uniform: {} colours",
        distinct.len()
    );
    // Sky at the top is bright and blue-ish; the bottom (ground and grass) is greener.
    let top = png.get_pixel(32, 1).0;
    assert!(top[2] > top[1] && top[2] > 150, "sky pixel {top:?}");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn exr_output_is_identical_for_any_thread_count() {
    let dir = temp_dir("exr");
    let mut images = Vec::new();
    for threads in ["1", "2", "4"] {
        let out = dir.join(format!("t{threads}.exr"));
        let run = sylva(&[
            "render",
            "--width",
            "64",
            "--height",
            "40",
            "--spp",
            "2",
            "--threads",
            threads,
            "--quiet",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(
            run.status.success(),
            "stderr: {}",
            String::from_utf8_lossy(&run.stderr)
        );
        images.push(read_exr(&out));
    }
    assert!(images[0].iter().all(|p| p.iter().all(|c| c.is_finite())));
    assert!(
        images[0].iter().any(|p| p[0] != images[0][0][0]),
        "uniform EXR"
    );
    let bits = |img: &Vec<[f32; 4]>| {
        img.iter()
            .flat_map(|p| p.map(f32::to_bits))
            .collect::<Vec<_>>()
    };
    assert_eq!(bits(&images[0]), bits(&images[1]), "1 vs 2 threads");
    assert_eq!(bits(&images[0]), bits(&images[2]), "1 vs 4 threads");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn bad_arguments_are_clear_errors_not_panics() {
    let dir = temp_dir("bad");
    let cases: Vec<(Vec<String>, &str)> = vec![
        (vec!["render".into(), "--width".into(), "0".into()], "width"),
        (vec!["render".into(), "--spp".into(), "lots".into()], "spp"),
        (
            vec![
                "render".into(),
                "--out".into(),
                dir.join("x.bmp").to_string_lossy().into(),
            ],
            "x.bmp",
        ),
        (
            vec![
                "render".into(),
                "--out".into(),
                dir.join("missing/x.png").to_string_lossy().into(),
            ],
            "does not exist",
        ),
        (
            vec!["render".into(), "--scene".into(), "jungle".into()],
            "unknown scene 'jungle'",
        ),
        (
            vec!["info".into(), "--scene".into(), "jungle".into()],
            "available: meadow",
        ),
        (
            vec![
                "render".into(),
                "--exposure".into(),
                "NaN".into(),
                "--out".into(),
                dir.join("x.png").to_string_lossy().into(),
            ],
            "exposure",
        ),
    ];
    for (args, expected) in cases {
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let run = sylva(&refs);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(!run.status.success(), "{args:?} succeeded");
        assert_ne!(run.status.code(), Some(101), "{args:?} panicked: {stderr}");
        assert!(
            stderr.contains(expected),
            "{args:?}: stderr lacks '{expected}': {stderr}"
        );
    }
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn info_prints_the_scene_statistics() {
    let run = sylva(&["info", "--scene", "meadow"]);
    assert!(run.status.success());
    let stdout = String::from_utf8_lossy(&run.stdout);
    for key in [
        "species          3",
        "unique triangles",
        "instances",
        "instanced tris",
        "memory",
        "TLAS",
    ] {
        assert!(stdout.contains(key), "info lacks '{key}': {stdout}");
    }
}

#[test]
fn help_explains_the_commands() {
    let run = sylva(&["render", "--help"]);
    let stdout = String::from_utf8_lossy(&run.stdout);
    for flag in [
        "--scene",
        "--width",
        "--height",
        "--spp",
        "--threads",
        "--seed",
        "--out",
    ] {
        assert!(stdout.contains(flag), "--help lacks {flag}");
    }
}

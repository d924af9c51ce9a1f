//! `sylva animate` end to end: the images of a swaying meadow are the same bytes on any
//! number of threads and after a resume, and a bad output pattern is refused by name.

use std::path::{Path, PathBuf};
use std::process::Command;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sylva-animate-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Runs `sylva animate` on the default meadow at 64×48, 0.4 s at 10 fps, into `dir`.
fn animate(dir: &Path, extra: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_sylva"))
        .args(["animate", "--seconds", "0.4", "--fps", "10"])
        .args([
            "--width",
            "64",
            "--height",
            "48",
            "--preset",
            "interactive",
            "--quiet",
        ])
        .arg("--out")
        .arg(dir.join("f_%02d.exr"))
        .args(extra)
        .output()
        .unwrap()
}

fn images(dir: &Path) -> Vec<Vec<u8>> {
    (0..4)
        .map(|k| {
            let path = dir.join(format!("f_{k:02}.exr"));
            std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        })
        .collect()
}

#[test]
fn images_are_the_same_on_any_threads_and_after_a_resume() {
    let (one, two) = (temp_dir("one"), temp_dir("two"));
    for (dir, threads) in [(&one, "1"), (&two, "2")] {
        let run = animate(dir, &["--threads", threads]);
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
    }
    let whole = images(&one);
    assert_eq!(images(&two), whole, "1 and 2 threads");
    for pair in whole.windows(2) {
        assert_ne!(pair[0], pair[1], "consecutive images are the same");
    }
    // A run stopped after image 1: images 2 and 3 missing, continued with --resume.
    for k in [2, 3] {
        std::fs::remove_file(two.join(format!("f_{k:02}.exr"))).unwrap();
    }
    let resumed = animate(&two, &["--resume"]);
    assert!(
        resumed.status.success(),
        "{}",
        String::from_utf8_lossy(&resumed.stderr)
    );
    assert_eq!(images(&two), whole, "resumed at image 2");
    let nothing_left = animate(&two, &["--resume"]);
    assert!(String::from_utf8_lossy(&nothing_left.stderr).contains("already"));
    std::fs::remove_dir_all(&one).ok();
    std::fs::remove_dir_all(&two).ok();
}

#[test]
fn an_output_without_an_image_number_is_refused() {
    let dir = temp_dir("bad");
    let run = Command::new(env!("CARGO_BIN_EXE_sylva"))
        .args(["animate", "--seconds", "1", "--out"])
        .arg(dir.join("frame.png"))
        .output()
        .unwrap();
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("frame.png") && stderr.contains("%d"),
        "{stderr}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_preview_is_an_animated_png_of_every_image_also_after_a_resume() {
    let dir = temp_dir("preview");
    let preview = dir.join("preview.png");
    let run = |extra: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_sylva"))
            .args(["animate", "--seconds", "0.3", "--fps", "10"])
            .args([
                "--width",
                "32",
                "--height",
                "24",
                "--preset",
                "interactive",
                "--quiet",
            ])
            .arg("--out")
            .arg(dir.join("f_%d.png"))
            .arg("--preview")
            .arg(&preview)
            .args(extra)
            .output()
            .unwrap()
    };
    let first = run(&[]);
    assert!(
        first.status.success(),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    let frames = |path: &Path| {
        let mut reader =
            png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()))
                .read_info()
                .unwrap();
        let count = reader
            .info()
            .animation_control()
            .map_or(1, |a| a.num_frames);
        (0..count)
            .map(|_| {
                let mut buffer = vec![0; reader.output_buffer_size().unwrap()];
                let info = reader.next_frame(&mut buffer).unwrap();
                buffer.truncate(info.buffer_size());
                buffer
            })
            .collect::<Vec<_>>()
    };
    let shown = frames(&preview);
    assert_eq!(shown.len(), 3);
    for (k, frame) in shown.iter().enumerate() {
        assert_eq!(
            frame,
            &frames(&dir.join(format!("f_{k}.png")))[0],
            "image {k}"
        );
    }
    // Resumed after image 0, the preview still holds all three.
    std::fs::remove_file(dir.join("f_1.png")).unwrap();
    std::fs::remove_file(dir.join("f_2.png")).unwrap();
    let resumed = run(&["--resume"]);
    assert!(
        resumed.status.success(),
        "{}",
        String::from_utf8_lossy(&resumed.stderr)
    );
    assert_eq!(frames(&preview), shown);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_scene_files_camera_path_sets_the_length_and_moves_the_view() {
    let dir = temp_dir("path");
    let scene = dir.join("flight.toml");
    std::fs::write(
        &scene,
        "preset = \"meadow\"\n\
         [[camera.path]]\ntime = 0\neye = [0, 45]\ntarget = [0, 0]\n\
         [[camera.path]]\ntime = 0.25\neye = [10, 30]\neye_height = 6\ntarget = [0, 0]\n",
    )
    .unwrap();
    let scene_arg = scene.to_str().unwrap();
    let out = dir.join("f_%d.png");
    animate_still_camera(
        &[
            "--scene", scene_arg, "--fps", "10", "--width", "32", "--height", "24",
        ],
        &out,
    );
    // 0.25 s at 10 fps: images at 0, 0.1 and 0.2 s.
    let written: Vec<Vec<u8>> = (0..3)
        .map(|k| std::fs::read(dir.join(format!("f_{k}.png"))).unwrap())
        .collect();
    assert!(!dir.join("f_3.png").exists());
    assert_ne!(written[0], written[1], "the camera moved (the wind is off)");
    assert_ne!(written[1], written[2]);

    let no_length = Command::new(env!("CARGO_BIN_EXE_sylva"))
        .args(["animate", "--quiet", "--out"])
        .arg(dir.join("g_%d.png"))
        .output()
        .unwrap();
    assert!(!no_length.status.success());
    assert!(String::from_utf8_lossy(&no_length.stderr).contains("give --seconds"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_gltf_animation_plays_for_its_length_the_same_on_any_threads() {
    let cube = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/gltf/AnimatedCube/glTF/AnimatedCube.gltf");
    let run = |dir: &Path, threads: &str| {
        let cube_arg = cube.to_str().unwrap();
        let args = [
            "--gltf", cube_arg, "--fps", "4", "--width", "48", "--height", "36",
        ];
        animate_still_camera(
            &[&args[..], &["--threads", threads]].concat(),
            &dir.join("f_%d.exr"),
        );
        let mut images = Vec::new();
        while let Ok(bytes) = std::fs::read(dir.join(format!("f_{}.exr", images.len()))) {
            images.push(bytes);
        }
        images
    };
    let (one, two) = (temp_dir("cube1"), temp_dir("cube2"));
    let images = run(&one, "1");
    // No --seconds: the file's animation decides (its keys end at 2 s: 8 images at 4 fps).
    assert_eq!(images.len(), 8);
    assert_ne!(images[0], images[1], "the cube turns");
    assert_eq!(run(&two, "2"), images, "1 and 2 threads");
    std::fs::remove_dir_all(&one).ok();
    std::fs::remove_dir_all(&two).ok();
}

/// Runs `sylva animate ARGS --preset interactive --wind off --quiet --out OUT`, which must
/// succeed (only the camera or the file's animation moves).
fn animate_still_camera(args: &[&str], out: &Path) {
    let run = Command::new(env!("CARGO_BIN_EXE_sylva"))
        .arg("animate")
        .args(args)
        .args([
            "--preset",
            "interactive",
            "--wind",
            "off",
            "--quiet",
            "--out",
        ])
        .arg(out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
}

//! `--profile` end to end: `render` and `animate` write one CSV row per frame with every
//! stage, the tile times of the last frame and a summary; the image does not change;
//! `sylva profile` plots the file; bad paths and files are refused by name.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sylva-profile-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn sylva(args: &[&str], paths: &[&Path]) -> Output {
    let mut command = Command::new(env!("CARGO_BIN_EXE_sylva"));
    command.args(args);
    for path in paths {
        command.arg(path);
    }
    command.output().unwrap()
}

fn render(out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "render",
        "--width",
        "64",
        "--height",
        "48",
        "--frames",
        "3",
        "--preset",
        "interactive",
        "--threads",
        "2",
    ];
    args.extend_from_slice(extra);
    args.push("--out");
    sylva(&args, &[out])
}

fn ok(output: &Output) -> String {
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

#[test]
fn a_profiled_render_logs_every_frame_and_renders_the_same_image() {
    let dir = temp_dir("render");
    let csv = dir.join("run.csv");
    let plain = ok(&render(&dir.join("plain.exr"), &[]));
    let stdout = ok(&render(
        &dir.join("profiled.exr"),
        &["--profile", csv.to_str().unwrap()],
    ));
    assert!(!plain.contains("profile of"));
    for line in [
        "profile of 3 frames",
        "render_tiles",
        "filter_display",
        "frame ",
        "1 rebuilds, 0 refits, 2 kept",
    ] {
        assert!(stdout.contains(line), "{line:?} in\n{stdout}");
    }
    assert_eq!(
        std::fs::read(dir.join("plain.exr")).unwrap(),
        std::fs::read(dir.join("profiled.exr")).unwrap(),
        "profiling does not change the image"
    );

    let text = std::fs::read_to_string(&csv).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 4, "a header and one row per frame:\n{text}");
    let header: Vec<&str> = lines[0].split(',').collect();
    let column = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .unwrap_or_else(|| panic!("{name}"))
    };
    for (frame, line) in lines[1..].iter().enumerate() {
        let fields: Vec<&str> = line.split(',').collect();
        assert_eq!(fields.len(), header.len());
        assert_eq!(fields[0], frame.to_string());
        let wall: f64 = fields[column("wall_ms")].parse().unwrap();
        let stages: f64 = [
            "animate",
            "prepare",
            "plan",
            "render",
            "accumulate",
            "display",
            "output",
        ]
        .iter()
        .map(|s| {
            fields[column(&format!("stage_{s}_ms"))]
                .parse::<f64>()
                .unwrap()
        })
        .sum::<f64>()
            + fields[column("write_ms")].parse::<f64>().unwrap();
        assert!(
            (wall - stages).abs() < 0.01,
            "the frame is its stages: {wall} vs {stages}"
        );
        let render: f64 = fields[column("render_tiles_ms")].parse().unwrap();
        assert!(
            render > 0.0 && render <= fields[column("stage_render_ms")].parse::<f64>().unwrap()
        );
        assert_eq!(fields[column("camera_rays")], (64 * 48).to_string());
        let expected = if frame == 0 { "rebuild" } else { "kept" };
        assert_eq!(fields[column("top_level")], expected);
        // A static frame does not rebuild: its column is empty.
        assert_eq!(fields[column("rebuild_top_level_ms")].is_empty(), frame > 0);
    }
    let tiles = std::fs::read_to_string(dir.join("run.tiles.csv")).unwrap();
    // 64×48 in 16-pixel tiles.
    assert_eq!(tiles.lines().count(), 1 + 4 * 3, "{tiles}");

    let plot = dir.join("plot.png");
    let said = ok(&sylva(&["profile", "--out"], &[&plot, &csv]));
    assert!(said.contains("3 frames, 12 tiles"), "{said}");
    let png = std::fs::read(&plot).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn an_animation_profile_has_a_row_per_frame_with_the_sway_and_its_refits() {
    let dir = temp_dir("animate");
    let csv = dir.join("anim.csv");
    let mut command = Command::new(env!("CARGO_BIN_EXE_sylva"));
    let run = command
        .args([
            "animate",
            "--seconds",
            "0.3",
            "--fps",
            "10",
            "--width",
            "48",
            "--height",
            "32",
            "--preset",
            "interactive",
            "--frames-per-image",
            "2",
            "--quiet",
            "--profile",
        ])
        .arg(&csv)
        .arg("--out")
        .arg(dir.join("f_%02d.png"))
        .output()
        .unwrap();
    ok(&run);
    let text = std::fs::read_to_string(&csv).unwrap();
    let rows: Vec<&str> = text.lines().skip(1).collect();
    assert_eq!(rows.len(), 3 * 2, "3 images of 2 frames:\n{text}");
    let header: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    let column = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let field = |row: &str, name: &str| row.split(',').nth(column(name)).unwrap().to_owned();
    // The wind moves the plants once per image: the first frame of images 1 and 2 sways
    // and refits, the second frame of each image keeps the tree.
    let actions: Vec<String> = rows.iter().map(|r| field(r, "top_level")).collect();
    assert_eq!(
        actions,
        ["rebuild", "kept", "refit", "kept", "refit", "kept"]
    );
    assert!(!field(rows[2], "animate_ms").is_empty(), "the sway ran");
    // Writing an image belongs to its last frame.
    assert!(field(rows[1], "write_ms").parse::<f64>().unwrap() > 0.0);
    assert_eq!(field(rows[0], "write_ms"), "0.0000");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn bad_profile_paths_and_files_are_refused_by_name() {
    let dir = temp_dir("bad");
    let out = dir.join("x.png");
    let wrong = render(&out, &["--profile", "run.txt"]);
    assert!(!wrong.status.success());
    assert!(
        String::from_utf8_lossy(&wrong.stderr).contains("run.txt: the profile is written as CSV")
    );
    let missing = render(&out, &["--profile", "no/such/dir/run.csv"]);
    assert!(String::from_utf8_lossy(&missing.stderr).contains("no/such/dir does not exist"));

    let not_a_profile = dir.join("other.csv");
    std::fs::write(&not_a_profile, "a,b\n1,2\n").unwrap();
    let refused = sylva(&["profile", "--out"], &[&dir.join("p.png"), &not_a_profile]);
    assert!(!refused.status.success());
    let said = String::from_utf8_lossy(&refused.stderr);
    assert!(
        said.contains("other.csv: no column stage_animate_ms"),
        "{said}"
    );
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn adaptive_transparency_covers_only_the_first_frames_of_an_accumulation() {
    let dir = temp_dir("fade");
    let csv = dir.join("run.csv");
    let image = dir.join("image.png");
    ok(&sylva(
        &[
            "render",
            "--width",
            "64",
            "--height",
            "48",
            "--frames",
            "6",
            "--preset",
            "interactive",
            "--threads",
            "2",
            "--profile",
        ],
        &[&csv, Path::new("--out"), &image],
    ));
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let column = header
        .iter()
        .position(|&h| h == "holes_made_opaque")
        .expect("a holes_made_opaque column");
    let opaque: Vec<u64> = lines
        .filter(|l| !l.is_empty())
        .map(|l| l.split(',').nth(column).unwrap().parse().unwrap())
        .collect();
    assert_eq!(opaque.len(), 6, "{opaque:?}");
    // The meadow's grass makes holes opaque while the curve is on (the first four
    // frames, ADAPTIVE_TRANSPARENCY_FRAMES), none after.
    assert!(opaque[..4].iter().all(|&n| n > 0), "{opaque:?}");
    assert!(opaque[4..].iter().all(|&n| n == 0), "{opaque:?}");
    std::fs::remove_dir_all(&dir).ok();
}

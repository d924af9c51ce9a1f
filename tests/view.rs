//! `sylva view` in a real window on a real X server (Xvfb): a scripted walkthrough saves
//! what the window shows, which must be what `sylva render` makes of the same view, and
//! change when the camera moves. CI installs Xvfb (`.ci/run`); without `xvfb-run` these
//! tests open the window on `DISPLAY`, and without either they fail and say what to
//! install.
#![cfg(feature = "view")]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sylva-view-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Runs `sylva view ARGS` under `xvfb-run` (a private X server for the run), or on the
/// desktop's display when there is no Xvfb.
fn view_on_xvfb(args: &[&str]) -> Output {
    if Command::new("xvfb-run").arg("--help").output().is_ok() {
        return Command::new("xvfb-run")
            .args(["-a", "-s", "-screen 0 640x480x24"])
            .arg(env!("CARGO_BIN_EXE_sylva"))
            .arg("view")
            .args(args)
            .output()
            .expect("xvfb-run runs");
    }
    assert!(
        std::env::var_os("DISPLAY").is_some(),
        "the window tests need an X server: install Xvfb \
         (apt-get install xvfb xauth libx11-xcb1 libxcursor1 libxi6 libxrandr2 libxkbcommon-x11-0) \
         or run them in a desktop session"
    );
    Command::new(env!("CARGO_BIN_EXE_sylva"))
        .arg("view")
        .args(args)
        .output()
        .expect("the binary runs")
}

/// RGB bytes and size of a PNG.
fn rgb(path: &Path) -> (Vec<u8>, u32, u32) {
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())),
    ));
    let mut reader = decoder.read_info().unwrap();
    let mut buffer = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buffer).unwrap();
    let channels = info.color_type.samples();
    let pixels = buffer[..info.buffer_size()]
        .chunks_exact(channels)
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect();
    (pixels, info.width, info.height)
}

#[test]
fn a_scripted_walkthrough_shows_what_render_makes_and_changes_when_the_camera_moves() {
    let dir = temp_dir("walk");
    let (first, second) = (dir.join("start.png"), dir.join("moved.png"));
    let script = dir.join("walk.toml");
    std::fs::write(
        &script,
        format!(
            "[[step]]\nframes = 2\nscreenshot = {:?}\n\n[[step]]\nposition = [5, 3, 20]\nlook_at = [0, 1, 0]\nframes = 1\nscreenshot = {:?}\nquit = true\n",
            first.to_str().unwrap(),
            second.to_str().unwrap()
        ),
    )
    .unwrap();
    run_script(&script, &[]);

    // The window's first view after two frames is the interactive render's image.
    let (shown, w, h) = rgb(&first);
    assert_eq!((w, h), (96, 72));
    let expected = interactive_render(None, &dir.join("render.png"));
    let differing = changed_pixels(&shown, &expected);
    assert_eq!(differing, 0, "the window shows another image than render");

    // The screenshot says what it shows.
    let text = common::png_text(&first);
    assert_eq!(
        text.get("sylva.frames").map(String::as_str),
        Some("2"),
        "{text:?}"
    );
    assert_eq!(text.get("sylva.scene").map(String::as_str), Some("meadow"));
    assert!(text.contains_key("sylva.camera.position"));

    // Not blank, and the moved camera sees something else.
    let spread = shown.iter().max().unwrap() - shown.iter().min().unwrap();
    assert!(spread > 64, "a flat image (spread {spread})");
    let (moved, ..) = rgb(&second);
    let changed = changed_pixels(&shown, &moved);
    assert!(changed > 96 * 72 / 2, "only {changed} pixels changed");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn without_a_display_view_says_so_and_bad_scripts_name_their_line() {
    let run = Command::new(env!("CARGO_BIN_EXE_sylva"))
        .args(["view", "--width", "32", "--height", "24"])
        .env_remove("DISPLAY")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("no display") && stderr.contains("sylva render"),
        "{stderr}"
    );

    let dir = temp_dir("bad");
    let script = dir.join("bad.toml");
    std::fs::write(&script, "[[step]]\nframes = 2\nspin = true\n").unwrap();
    let run = Command::new(env!("CARGO_BIN_EXE_sylva"))
        .args(["view", "--script"])
        .arg(&script)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("bad.toml") && stderr.contains("spin") && stderr.contains("line 3"),
        "{stderr}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// Runs `sylva view` at 96×72 on the script at `path`, which must succeed.
/// Runs the walkthrough script `path` at 96×72 with `extra` arguments; it must succeed.
fn run_script(path: &Path, extra: &[&str]) -> Output {
    let args = [
        &[
            "--width",
            "96",
            "--height",
            "72",
            "--script",
            path.to_str().unwrap(),
        ][..],
        extra,
    ]
    .concat();
    let run = view_on_xvfb(&args);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    run
}

/// RGB bytes of `sylva render --preset interactive --frames 2` at 96×72 written to `out`,
/// of `scene` (a scene file) or the default scene.
fn interactive_render(scene: Option<&Path>, out: &Path) -> Vec<u8> {
    let mut command = Command::new(env!("CARGO_BIN_EXE_sylva"));
    command.arg("render");
    if let Some(scene) = scene {
        command.arg("--scene").arg(scene);
    }
    let render = command
        .args(["--preset", "interactive", "--frames", "2"])
        .args(["--width", "96", "--height", "72", "--quiet", "--out"])
        .arg(out)
        .output()
        .unwrap();
    assert!(
        render.status.success(),
        "{}",
        String::from_utf8_lossy(&render.stderr)
    );
    rgb(out).0
}

/// Pixels (RGB triples) that differ between two images of one size.
fn changed_pixels(a: &[u8], b: &[u8]) -> usize {
    a.chunks_exact(3)
        .zip(b.chunks_exact(3))
        .filter(|(p, q)| p != q)
        .count()
}

/// Runs `sylva view` at 96×72 on a script of `steps` (TOML bodies of `[[step]]` tables),
/// each followed by a screenshot; returns the screenshots' RGB bytes.
fn screenshots_of_steps(name: &str, steps: &[&str]) -> Vec<Vec<u8>> {
    let dir = temp_dir(name);
    let shot = |i: usize| dir.join(format!("step{i}.png"));
    let script: String = steps
        .iter()
        .enumerate()
        .map(|(i, step)| {
            format!(
                "[[step]]\n{step}\nscreenshot = {:?}\n\n",
                shot(i).to_str().unwrap()
            )
        })
        .collect();
    let path = dir.join("script.toml");
    std::fs::write(&path, script).unwrap();
    run_script(&path, &[]);
    let images = (0..steps.len()).map(|i| rgb(&shot(i)).0).collect();
    std::fs::remove_dir_all(&dir).ok();
    images
}

#[test]
fn edits_in_the_window_show_up_and_undo_restores_the_image_bit_for_bit() {
    // The default meadow at 96×72: pixel (63, 20) shows the big tree's crown; pixel
    // (20, 42) ground 7 m from every tree (the tree layer's spacing; the near grass
    // layer is full: no grass may be planted there).
    let images = screenshots_of_steps(
        "edit",
        &[
            "frames = 2",
            "select = [63, 20]\ndelete = true\nframes = 2",
            "undo = true\nframes = 2",
            "select = [63, 20]\ninsert = [20, 42]\nframes = 2",
            "undo = true\nframes = 2\nquit = true",
        ],
    );
    let deleted = changed_pixels(&images[0], &images[1]);
    assert!(deleted > 100, "deleting the tree changed {deleted} pixels");
    let after_undo = changed_pixels(&images[0], &images[2]);
    assert_eq!(
        after_undo, 0,
        "undoing the delete left {after_undo} pixels changed"
    );
    let inserted = changed_pixels(&images[0], &images[3]);
    assert!(inserted > 0, "the inserted plant is not seen");
    let after_undo = changed_pixels(&images[0], &images[4]);
    assert_eq!(
        after_undo, 0,
        "undoing the insert left {after_undo} pixels changed"
    );
}

#[test]
fn wind_sways_the_plants_and_calm_puts_every_one_back() {
    let images = screenshots_of_steps(
        "wind",
        &[
            "frames = 1",
            "wind = true\nframes = 1",
            "wind = false\nframes = 1\nquit = true",
        ],
    );
    let swayed = changed_pixels(&images[0], &images[1]);
    assert!(swayed > 100, "the wind moved {swayed} pixels");
    let after_calm = changed_pixels(&images[0], &images[2]);
    assert_eq!(after_calm, 0, "calm left {after_calm} pixels changed");
}

#[test]
fn a_saved_ecosystem_renders_what_the_window_showed() {
    let dir = temp_dir("save");
    let saved = dir.join("edited.toml");
    let images = screenshots_of_steps(
        "save-steps",
        &[
            "frames = 1",
            // A tree planted where the tree layer has room, then the big tree deleted.
            "select = [63, 20]\ninsert = [20, 42]\nframes = 1",
            &format!(
                "select = [63, 20]\ndelete = true\nsave = {:?}\nframes = 2\nquit = true",
                saved.to_str().unwrap()
            ),
        ],
    );
    assert!(
        changed_pixels(&images[0], &images[1]) > 0,
        "no tree planted"
    );
    let rendered = interactive_render(Some(&saved), &dir.join("render.png"));
    let differing = changed_pixels(&images[2], &rendered);
    assert_eq!(
        differing, 0,
        "the saved scene renders {differing} pixels differently"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_recorded_walkthrough_replays_to_the_same_scene_and_every_shown_frame_is_saved() {
    let dir = temp_dir("record");
    let (saved, recording, frames) = (
        dir.join("edited.toml"),
        dir.join("recorded.toml"),
        dir.join("frames"),
    );
    let script = dir.join("script.toml");
    std::fs::write(
        &script,
        format!(
            "[[step]]\nframes = 2\n\n\
             [[step]]\nselect = [63, 20]\ndelete = true\nframes = 2\n\n\
             [[step]]\nmap_insert = [1.5, 2.5]\nframes = 2\n\n\
             [[step]]\nposition = [5, 3, 20]\nlook_at = [0, 1, 0]\nframes = 2\n\n\
             [[step]]\nsave = {:?}\nquit = true\n",
            saved.to_str().unwrap()
        ),
    )
    .unwrap();
    let size = ["--width", "96", "--height", "72"];
    let record = view_on_xvfb(
        &[
            &size[..],
            &["--script", script.to_str().unwrap()],
            &["--record", recording.to_str().unwrap()],
            &["--frames-out", frames.to_str().unwrap()],
        ]
        .concat(),
    );
    assert!(
        record.status.success(),
        "{}",
        String::from_utf8_lossy(&record.stderr)
    );
    let edited = std::fs::read_to_string(&saved).unwrap();

    // The recording holds the camera's stops and the edits, and replays to the same scene.
    let text = std::fs::read_to_string(&recording).unwrap();
    for key in [
        "rotation",
        "delete = true",
        "map_insert",
        "save",
        "quit = true",
    ] {
        assert!(text.contains(key), "no {key} in the recording:\n{text}");
    }
    std::fs::remove_file(&saved).unwrap();
    let replay = view_on_xvfb(&[&size[..], &["--script", recording.to_str().unwrap()]].concat());
    assert!(
        replay.status.success(),
        "{}",
        String::from_utf8_lossy(&replay.stderr)
    );
    assert_eq!(
        std::fs::read_to_string(&saved).unwrap(),
        edited,
        "the replayed walkthrough saved another scene"
    );

    // Every shown frame was saved; none is blank, and the accumulation restarts (with a
    // changed image) after the delete, the insert and the move.
    let mut files: Vec<PathBuf> = std::fs::read_dir(&frames)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    assert!(files.len() >= 8, "{} frames saved", files.len());
    let mut restarts = 0;
    let mut previous: Option<(u32, Vec<u8>)> = None;
    for file in &files {
        let (pixels, w, h) = rgb(file);
        assert_eq!((w, h), (96, 72));
        assert!(
            pixels.chunks_exact(3).any(|p| p != &pixels[..3]),
            "{} is blank",
            file.display()
        );
        let accumulated: u32 = common::png_text(file)["sylva.frames"].parse().unwrap();
        if let Some((count, image)) = &previous
            && accumulated <= *count
        {
            restarts += 1;
            assert!(
                changed_pixels(image, &pixels) > 0,
                "{} restarted without a change",
                file.display()
            );
        }
        previous = Some((accumulated, pixels));
    }
    assert!(restarts >= 3, "{restarts} restarts among the shown frames");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_overview_key_jumps_above_the_ecosystem_and_back_to_the_same_view() {
    let images = screenshots_of_steps(
        "overview",
        &[
            "frames = 2",
            "overview = true\nframes = 1",
            "overview = false\nframes = 2\nquit = true",
        ],
    );
    let jumped = changed_pixels(&images[0], &images[1]);
    assert!(
        jumped > 96 * 72 / 2,
        "the overview changed only {jumped} pixels"
    );
    let back = changed_pixels(&images[0], &images[2]);
    assert_eq!(back, 0, "back at the scene's camera {back} pixels differ");
}

#[test]
fn a_scene_that_fails_to_load_leaves_the_shown_one_and_a_good_one_replaces_it() {
    let dir = temp_dir("open");
    let (good, broken) = (dir.join("good.toml"), dir.join("broken.toml"));
    std::fs::write(&broken, "[scene]\nname = \"broken\"\nlayers = 3\n").unwrap();
    let shot = |i: usize| dir.join(format!("open{i}.png"));
    let script = dir.join("script.toml");
    std::fs::write(
        &script,
        format!(
            "[[step]]\nsave = {good:?}\nframes = 2\nscreenshot = {:?}\n\n\
             [[step]]\nopen = {broken:?}\nframes = 1\nscreenshot = {:?}\n\n\
             [[step]]\nopen = {good:?}\nframes = 2\nscreenshot = {:?}\nquit = true\n",
            shot(0),
            shot(1),
            shot(2),
        ),
    )
    .unwrap();
    let run = view_on_xvfb(&[
        "--width",
        "96",
        "--height",
        "72",
        "--script",
        script.to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(
        stderr.contains("broken.toml") && stderr.contains("kept meadow"),
        "the failed load is not reported with its file: {stderr}"
    );
    let [before, kept, reopened] = [0, 1, 2].map(|i| rgb(&shot(i)).0);
    assert!(
        kept.chunks_exact(3).any(|p| p != &kept[..3]),
        "the window went blank after the failed load"
    );
    assert!(
        changed_pixels(&before, &kept) < 96 * 72 / 2,
        "another scene is shown"
    );
    // The saved meadow, loaded in its place at the same camera, is the same image.
    assert_eq!(changed_pixels(&before, &reopened), 0);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_profiled_window_logs_every_shown_frame() {
    let dir = temp_dir("profile");
    let script = dir.join("walk.toml");
    std::fs::write(&script, "[[step]]\nframes = 3\nquit = true\n").unwrap();
    let csv = dir.join("view.csv");
    let run = run_script(
        &script,
        &["--threads", "2", "--profile", csv.to_str().unwrap()],
    );
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(stdout.contains("profile of"), "{stdout}");
    let text = std::fs::read_to_string(&csv).unwrap();
    let rows = text.lines().count() - 1;
    assert!(rows >= 3, "at least the 3 frames waited for:\n{text}");
    let header: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    let render = header.iter().position(|h| *h == "render_tiles_ms").unwrap();
    for row in text.lines().skip(1) {
        let value = row.split(',').nth(render).unwrap();
        assert!(
            value.parse::<f64>().unwrap() > 0.0,
            "every shown frame rendered: {row}"
        );
    }
    assert!(dir.join("view.tiles.csv").exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// Holds W for two seconds in the real window (X key events from `xdotool`, as a user's
/// keyboard sends them) and returns the shown frames' files with their write times, and
/// when the key went down and came up (seconds since the epoch).
fn hold_w_in_the_window(dir: &Path) -> (Vec<(f64, PathBuf)>, f64, f64) {
    let frames = dir.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    assert!(
        Command::new("xdotool").arg("version").output().is_ok(),
        "the held-key test sends key events with xdotool: apt-get install xdotool"
    );
    // Inside the private X server: the window, its first frames, the key held, the window
    // closed. The times go to files the test reads.
    let script = format!(
        r#"{bin} view --scene meadow --width 320 --height 240 --threads 2 --frames-out {frames} &
view=$!
for i in $(seq 1 300); do [ -n "$(ls {frames})" ] && break; sleep 0.1; done
sleep 1
window=$(xdotool search --sync --onlyvisible --name sylva | head -1)
xdotool windowactivate --sync "$window" 2>/dev/null; xdotool windowfocus --sync "$window"
date +%s.%N > {dir}/down
xdotool keydown --window "$window" w
sleep 2
xdotool keyup --window "$window" w
date +%s.%N > {dir}/up
sleep 0.5
xdotool key --window "$window" Escape
wait $view"#,
        bin = env!("CARGO_BIN_EXE_sylva"),
        frames = frames.display(),
        dir = dir.display(),
    );
    let output = Command::new("xvfb-run")
        .args(["-a", "-s", "-screen 0 640x480x24", "sh", "-c", &script])
        .output()
        .expect("xvfb-run runs (apt-get install xvfb xauth)");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let time = |name: &str| -> f64 {
        let text = std::fs::read_to_string(dir.join(name)).unwrap();
        text.trim().parse().unwrap()
    };
    let mut shown: Vec<(f64, PathBuf)> = std::fs::read_dir(&frames)
        .unwrap()
        .map(|entry| {
            let path = entry.unwrap().path();
            let written = std::fs::metadata(&path).unwrap().modified().unwrap();
            let seconds = written
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_secs_f64();
            (seconds, path)
        })
        .collect();
    shown.sort_by(|a, b| a.0.total_cmp(&b.0));
    (shown, time("down"), time("up"))
}

#[test]
fn holding_a_movement_key_keeps_new_views_coming() {
    let dir = temp_dir("held");
    let (shown, down, up) = hold_w_in_the_window(&dir);
    // Frames keep reaching the screen while the key is down (every one of them used to
    // be given up for the next pose until the key came up), and they show the walk.
    let before = shown.iter().rfind(|(t, _)| *t < down);
    let held: Vec<&PathBuf> = shown
        .iter()
        .filter(|(t, _)| (down..=up).contains(t))
        .map(|(_, path)| path)
        .collect();
    assert!(
        held.len() >= 3,
        "{} frames shown while W was held for {:.1} s",
        held.len(),
        up - down
    );
    let mean_difference = |a: &[u8], b: &[u8]| {
        a.iter()
            .zip(b)
            .map(|(&p, &q)| f64::from(p.abs_diff(q)))
            .sum::<f64>()
            / a.len() as f64
    };
    let (at_rest, ..) = rgb(&before.expect("a frame before the key went down").1);
    let (walked, ..) = rgb(held.last().unwrap());
    let moved = mean_difference(&at_rest, &walked);
    assert!(
        moved > 12.0,
        "the last held frame differs by only {moved:.1} levels a channel"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_script_holds_a_key_and_counts_the_frames_shown_meanwhile() {
    let dir = temp_dir("hold");
    let (start, walked) = (dir.join("start.png"), dir.join("walked.png"));
    let script = dir.join("hold.toml");
    std::fs::write(
        &script,
        format!(
            "[[step]]\nframes = 1\nscreenshot = {:?}\n\n[[step]]\nhold = \"w\"\nseconds = 1.5\nscreenshot = {:?}\nquit = true\n",
            start.to_str().unwrap(),
            walked.to_str().unwrap()
        ),
    )
    .unwrap();
    let run = run_script(&script, &[]);
    let stdout = String::from_utf8_lossy(&run.stdout);
    let line = stdout
        .lines()
        .find(|l| l.contains("held keys:"))
        .unwrap_or_else(|| panic!("no held-keys line in {stdout}"));
    let frames: u32 = line
        .split("held keys: ")
        .nth(1)
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{line}"));
    assert!(frames >= 3, "{line}");
    assert!(line.contains("in 1.5 s"), "{line}");
    // The key moved the camera: the view after the hold is another one.
    let (before, ..) = rgb(&start);
    let (after, ..) = rgb(&walked);
    assert!(changed_pixels(&before, &after) > 96 * 72 / 2);
    std::fs::remove_dir_all(&dir).ok();
}

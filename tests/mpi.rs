//! `sylva render` under `mpirun` (feature `mpi`; needs Open MPI's `mpirun`): images bit
//! for bit those of one process for any ranks and threads, checkpoints that resume on
//! other rank counts, and every failure — a different scene on one rank, a scene one
//! rank cannot load, a rank killed mid-run, Ctrl-C — a clear end in bounded time.
#![cfg(feature = "mpi")]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// One mpirun at a time: each uses every core of the machine.
static MPIRUN: Mutex<()> = Mutex::new(());

const SYLVA: &str = env!("CARGO_BIN_EXE_sylva");

/// The forest at 96×72, interactive quality: every stage in play, frames of ~10 ms.
const FOREST_INTERACTIVE: [&str; 8] = [
    "--scene",
    "forest",
    "--width",
    "96",
    "--height",
    "72",
    "--preset",
    "interactive",
];

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sylva-mpi-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// `mpirun` with one app context per entry (ranks, `sylva` arguments).
fn mpirun_command(contexts: &[(usize, Vec<String>)]) -> Command {
    let mut command = Command::new("mpirun");
    command.args(["--allow-run-as-root", "--oversubscribe"]);
    for (i, (ranks, args)) in contexts.iter().enumerate() {
        if i > 0 {
            command.arg(":");
        }
        command.args(["-np", &ranks.to_string(), SYLVA]).args(args);
    }
    command
}

/// Runs to the end, at most `limit`; panics when it takes longer.
fn run_bounded(mut command: Command, limit: Duration) -> (Output, Duration) {
    let start = Instant::now();
    let mut child = command
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("mpirun runs (install openmpi-bin)");
    wait_bounded(&mut child, start, limit);
    (child.wait_with_output().unwrap(), start.elapsed())
}

fn wait_bounded(child: &mut Child, start: Instant, limit: Duration) {
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > limit {
            let _ = child.kill();
            panic!("still running after {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn args(list: &[&str]) -> Vec<String> {
    list.iter().map(|s| s.to_string()).collect()
}

/// `sylva` with `list` on `ranks` ranks, which must succeed within two minutes;
/// returns what rank 0 printed.
fn succeeds_on(ranks: usize, list: Vec<String>) -> String {
    let (output, _) = run_bounded(mpirun_command(&[(ranks, list)]), Duration::from_secs(120));
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// `sylva render` alone.
fn alone(list: &[&str]) {
    let output = Command::new(SYLVA).args(list).output().unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

fn bytes(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn still_and_progressive_images_are_one_process_images_bit_for_bit_on_1_2_3_ranks() {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("same");
    let progressive = [&FOREST_INTERACTIVE[..], &["--frames", "4"]].concat();
    let renders: [(&str, &[&str]); 2] = [
        (
            "still",
            &["--width", "96", "--height", "72", "--preset", "still"],
        ),
        ("progressive", &progressive),
    ];
    for (name, settings) in renders {
        let reference = dir.join(format!("{name}.exr"));
        let mut list = vec!["render", "-q", "--out", reference.to_str().unwrap()];
        list.extend_from_slice(settings);
        alone(&list);
        for (ranks, threads) in [(1, 1), (2, 1), (3, 1), (2, 2)] {
            let out = dir.join(format!("{name}_{ranks}x{threads}.exr"));
            let mut list = args(&["render", "--threads", &threads.to_string()]);
            list.extend(args(&["--out", out.to_str().unwrap()]));
            list.extend(args(settings));
            let stdout = succeeds_on(ranks, list);
            assert!(
                bytes(&out) == bytes(&reference),
                "{name}: {ranks} ranks × {threads} threads differ from one process"
            );
            // Only rank 0 prints; in a cluster run it says what the others did.
            assert_eq!(stdout.matches(" -> ").count(), 1, "{stdout}");
            assert_eq!(
                stdout.contains(&format!("cluster: {ranks} ranks")),
                ranks > 1,
                "{stdout}"
            );
        }
    }
}

#[test]
fn a_checkpoint_resumes_on_another_number_of_ranks() {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("resume");
    let settings = FOREST_INTERACTIVE;
    let reference = dir.join("reference.exr");
    let mut list = vec![
        "render",
        "-q",
        "--frames",
        "4",
        "--out",
        reference.to_str().unwrap(),
    ];
    list.extend_from_slice(&settings);
    alone(&list);
    let checkpoint = dir.join("half.checkpoint");
    let (half, resumed) = (dir.join("half.exr"), dir.join("resumed.exr"));
    for (ranks, frames, extra) in [
        (3, "2", ["--checkpoint", checkpoint.to_str().unwrap()]),
        (2, "4", ["--resume", checkpoint.to_str().unwrap()]),
    ] {
        let out = if extra[0] == "--checkpoint" {
            &half
        } else {
            &resumed
        };
        let mut list = args(&["render", "-q", "--threads", "1", "--frames", frames]);
        list.extend(args(&extra));
        list.extend(args(&["--out", out.to_str().unwrap()]));
        list.extend(args(&settings));
        succeeds_on(ranks, list);
    }
    assert!(bytes(&resumed) == bytes(&reference));
}

/// Three ranks; rank 1 is given `rank_1_extra` on top of the others' arguments.
fn with_rank_1_given(dir: &Path, rank_1_extra: &[&str]) -> (Output, Duration) {
    let out = dir.join("out.exr");
    let common = args(&[
        "render",
        "--threads",
        "1",
        "--width",
        "64",
        "--height",
        "48",
        "--out",
        out.to_str().unwrap(),
    ]);
    let mut odd = common.clone();
    odd.extend(args(rank_1_extra));
    run_bounded(
        mpirun_command(&[(1, common.clone()), (1, odd), (1, common)]),
        Duration::from_secs(60),
    )
}

#[test]
fn a_rank_that_would_render_another_scene_is_refused_by_name() {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("mismatch");
    // Translucency changes only the shaders: the hash must cover them too.
    let (output, took) = with_rank_1_given(&dir, &["--translucency", "off"]);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(
        stderr.contains("error: rank 1 would render a different scene"),
        "{stderr}"
    );
    assert_eq!(stderr.matches("error:").count(), 1, "said once: {stderr}");
    assert!(!dir.join("out.exr").exists(), "no frame was complete");
    assert!(took < Duration::from_secs(30), "took {took:?}");
}

#[test]
fn a_rank_that_cannot_load_the_scene_is_named_with_its_error() {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("load");
    let missing = dir.join("missing.toml");
    let (output, took) = with_rank_1_given(&dir, &["--scene", missing.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(
        stderr.contains("error: rank 1 could not build the scene: ")
            && stderr.contains("missing.toml"),
        "{stderr}"
    );
    assert!(took < Duration::from_secs(30), "took {took:?}");
}

/// The pid of rank `rank` of the run writing `out`.
fn rank_pid(rank: usize, out: &Path) -> Option<u32> {
    let wanted = format!("OMPI_COMM_WORLD_RANK={rank}");
    std::fs::read_dir("/proc")
        .ok()?
        .flatten()
        .find_map(|entry| {
            let pid: u32 = entry.file_name().to_str()?.parse().ok()?;
            let cmdline = std::fs::read(entry.path().join("cmdline")).ok()?;
            let environ = std::fs::read(entry.path().join("environ")).ok()?;
            let has =
                |bytes: &[u8], text: &str| bytes.split(|&b| b == 0).any(|s| s == text.as_bytes());
            (has(&cmdline, out.to_str()?) && has(&cmdline, SYLVA) && has(&environ, &wanted))
                .then_some(pid)
        })
}

/// Sends `signal` (`-KILL`, `-INT`, …) to process `pid`.
fn signal(signal: &str, pid: u32) {
    let sent = Command::new("kill")
        .args([signal, &pid.to_string()])
        .status()
        .unwrap();
    assert!(sent.success(), "kill {signal} {pid}");
}

/// Waits at most 30 s for the run to end, which must be a failure; returns its stderr.
fn ends_failing(mut child: Child) -> String {
    wait_bounded(&mut child, Instant::now(), Duration::from_secs(30));
    let output = child.wait_with_output().unwrap();
    assert!(!output.status.success());
    String::from_utf8_lossy(&output.stderr).into_owned()
}

/// A long progressive run on 3 ranks with a checkpoint every second; returns the child
/// once its first checkpoint is written, and the image and checkpoint paths.
fn long_run(dir: &Path, extra: &[&str]) -> (Child, PathBuf, PathBuf) {
    let out = dir.join("long.exr");
    let mut list = args(&["render"]);
    list.extend(args(&FOREST_INTERACTIVE));
    list.extend(args(extra));
    list.extend(args(&[
        "--threads",
        "1",
        "--frames",
        "1000000",
        "--checkpoint-every",
        "1s",
        "--out",
        out.to_str().unwrap(),
    ]));
    let mut child = mpirun_command(&[(3, list)])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("mpirun runs");
    let checkpoint = out.with_extension("checkpoint");
    let start = Instant::now();
    while !checkpoint.exists() {
        if start.elapsed() > Duration::from_secs(90) || child.try_wait().unwrap().is_some() {
            let _ = child.kill();
            let output = child.wait_with_output().unwrap();
            panic!("no checkpoint: {}", String::from_utf8_lossy(&output.stderr));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    (child, out, checkpoint)
}

/// The checkpoint continues in a single process for half a second.
fn resumes(checkpoint: &Path, dir: &Path) {
    let out = dir.join("continued.exr");
    let mut list = vec!["render", "-q"];
    list.extend_from_slice(&FOREST_INTERACTIVE);
    list.extend_from_slice(&[
        "--time",
        "500ms",
        "--resume",
        checkpoint.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    alone(&list);
}

#[test]
fn a_rank_killed_mid_run_ends_it_in_bounded_time_with_the_image_and_a_checkpoint() {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("killed");
    let (child, out, checkpoint) = long_run(&dir, &[]);
    std::thread::sleep(Duration::from_millis(1500));
    let pid = rank_pid(1, &out).expect("rank 1 is running");
    signal("-KILL", pid);
    let stderr = ends_failing(child);
    assert!(stderr.contains("rank 1"), "the rank is named: {stderr}");
    assert!(out.exists() && checkpoint.exists());
    resumes(&checkpoint, &dir);
}

#[test]
fn ctrl_c_on_mpirun_writes_the_image_and_a_checkpoint() {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("interrupt");
    let (child, out, checkpoint) = long_run(&dir, &[]);
    std::fs::remove_file(&checkpoint).unwrap();
    signal("-INT", child.id());
    let stderr = ends_failing(child);
    assert!(stderr.contains("interrupted: writing the "), "{stderr}");
    assert!(out.exists() && checkpoint.exists(), "{stderr}");
    resumes(&checkpoint, &dir);
}

#[test]
fn animate_writes_one_process_images_on_3_ranks() {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("animate");
    let settings = [
        "animate",
        "-q",
        "--seconds",
        "0.5",
        "--fps",
        "8",
        "--width",
        "64",
        "--height",
        "48",
        "--frames-per-image",
        "2",
    ];
    let (alone_dir, cluster_dir) = (dir.join("alone"), dir.join("cluster"));
    let pattern = |d: &Path| d.join("f_%02d.exr").to_str().unwrap().to_owned();
    let mut list = settings.to_vec();
    let alone_out = pattern(&alone_dir);
    list.extend(["--out", &alone_out]);
    alone(&list);
    let mut list = args(&settings);
    list.extend(args(&["--threads", "1", "--out", &pattern(&cluster_dir)]));
    succeeds_on(3, list);
    for k in 0..4 {
        let name = format!("f_{k:02}.exr");
        assert!(
            bytes(&alone_dir.join(&name)) == bytes(&cluster_dir.join(&name)),
            "{name} differs"
        );
    }
    assert!(!cluster_dir.join("f_04.exr").exists());
}

#[test]
fn a_hung_rank_is_named_after_the_time_limit_and_the_run_ends_with_what_it_has() {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("hung");
    let (child, out, checkpoint) = long_run(&dir, &["--cluster-timeout", "3s"]);
    std::fs::remove_file(&checkpoint).unwrap();
    let pid = rank_pid(2, &out).expect("rank 2 is running");
    signal("-STOP", pid);
    let stderr = ends_failing(child);
    assert!(
        stderr.contains("error: rank 2 sent nothing for 3."),
        "the silent rank is named: {stderr}"
    );
    assert!(stderr.contains("rendered before the failure"), "{stderr}");
    assert!(out.exists() && checkpoint.exists(), "{stderr}");
    resumes(&checkpoint, &dir);
}

#[test]
fn converge_on_3_ranks_renders_the_one_process_reference_and_measures_every_setting() {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("converge");
    let settings = [
        "converge",
        "-q",
        "--width",
        "48",
        "--height",
        "36",
        "--configs",
        "interactive,still",
        "--budget",
        "1s",
        "--reference-frames",
        "2",
    ];
    let (alone_dir, cluster_dir) = (dir.join("alone"), dir.join("cluster"));
    let alone_out = alone_dir.to_str().unwrap().to_owned();
    let mut list = settings.to_vec();
    list.extend(["--out", &alone_out]);
    alone(&list);
    // Twice: the second run takes the reference rank 0 cached, the others follow.
    for _ in 0..2 {
        let mut list = args(&settings);
        list.extend(args(&[
            "--threads",
            "1",
            "--out",
            cluster_dir.to_str().unwrap(),
        ]));
        let stdout = succeeds_on(3, list);
        assert!(
            bytes(&alone_dir.join("reference.film")) == bytes(&cluster_dir.join("reference.film"))
        );
        let csv = std::fs::read_to_string(cluster_dir.join("error_vs_time.csv")).unwrap();
        for setting in ["interactive", "still"] {
            assert!(csv.lines().any(|l| l.starts_with(setting)), "{csv}");
            assert_eq!(stdout.matches(setting).count(), 1, "{stdout}");
        }
    }
}

/// `command` under `xvfb-run` (a private X server), or on the desktop's display when
/// there is no Xvfb.
fn on_xvfb(command: Command) -> Command {
    if Command::new("xvfb-run").arg("--help").output().is_err() {
        return command;
    }
    let mut wrapped = Command::new("xvfb-run");
    wrapped
        .args(["-a", "-s", "-screen 0 640x480x24"])
        .arg(command.get_program())
        .args(command.get_args());
    wrapped
}

#[test]
fn view_on_3_ranks_shows_what_one_window_shows_through_moves_and_edits() {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("view");
    // The default meadow at 96×72: pixel (63, 20) shows the big tree's crown.
    let steps = [
        "frames = 2",
        "select = [63, 20]\ndelete = true\nframes = 2",
        "position = [5, 3, 20]\nlook_at = [0, 1, 0]\nframes = 3",
        "undo = true\nselect = [40, 30]\ninsert = [20, 42]\nframes = 2\nquit = true",
    ];
    let script = |name: &str| {
        let text: String = steps
            .iter()
            .enumerate()
            .map(|(i, step)| {
                let shot = dir.join(format!("{name}{i}.png"));
                format!(
                    "[[step]]\n{step}\nscreenshot = {:?}\n\n",
                    shot.to_str().unwrap()
                )
            })
            .collect();
        let path = dir.join(format!("{name}.toml"));
        std::fs::write(&path, text).unwrap();
        path.to_str().unwrap().to_owned()
    };
    let settings = ["view", "--width", "96", "--height", "72", "--script"];
    let mut window = Command::new(SYLVA);
    window.args(settings).arg(script("alone"));
    let (output, _) = run_bounded(on_xvfb(window), Duration::from_secs(120));
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );

    let mut list = args(&settings);
    list.extend([script("ranks"), "--cluster".into()]);
    let (output, _) = run_bounded(
        on_xvfb(mpirun_command(&[(3, list)])),
        Duration::from_secs(120),
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(stdout.contains("cluster: 3 ranks"), "{stdout}");
    for i in 0..steps.len() {
        let (alone, ranks) = (
            dir.join(format!("alone{i}.png")),
            dir.join(format!("ranks{i}.png")),
        );
        assert!(
            bytes(&alone) == bytes(&ranks),
            "step {i}: the window on 3 ranks shows another image than alone"
        );
    }
    assert!(bytes(&dir.join("alone0.png")) != bytes(&dir.join("alone1.png")));

    // --cluster outside mpirun, and a window per rank, are refused with what to do.
    let output = Command::new(SYLVA)
        .args(["view", "--cluster"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("mpirun -np N sylva view --cluster"),
        "{stderr}"
    );
    let (output, _) = run_bounded(
        mpirun_command(&[(2, args(&["view", "--width", "32", "--height", "24"]))]),
        Duration::from_secs(60),
    );
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(stderr.contains("needs --cluster"), "{stderr}");
}

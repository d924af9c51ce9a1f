//! Walkthrough camera control: held movement keys, mouse look and a speed setting turned
//! into the camera's [`Transform`], frame-rate independent (the window code only
//! translates its events into a [`FlyInput`]); and scripted walkthroughs, the replayable
//! camera stops that tests and benchmarks fly.

use glam::{EulerRot, Quat, Vec2, Vec3};
use sylva_engine::components::Transform;

/// Steepest look up or down, short of straight (where yaw is undefined).
const MAX_PITCH: f32 = 1.55;

/// Factor one scroll step changes the speed by.
pub const SPEED_STEP: f32 = 1.25;

/// A first-person camera: position, heading and pitch, and how fast it flies.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlyCamera {
    /// Where the camera stands.
    pub position: Vec3,
    /// Heading in radians around +Y (0 looks along −Z).
    pub yaw: f32,
    /// Radians above the horizon.
    pub pitch: f32,
    /// Metres per second at full key travel.
    pub speed: f32,
}

/// What the user asks of the camera over one step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FlyInput {
    /// Forward (+) or back (−), −1 ..= 1.
    pub forward: f32,
    /// Right (+) or left (−), −1 ..= 1.
    pub right: f32,
    /// Up (+) or down (−) along world +Y, −1 ..= 1.
    pub up: f32,
    /// Look change in radians: x turns right, y tilts up.
    pub look: Vec2,
    /// Speed steps (scroll): each multiplies the speed by [`SPEED_STEP`].
    pub speed_steps: f32,
}

impl FlyInput {
    /// True when the input moves or turns the camera.
    pub fn moves(&self) -> bool {
        self.forward != 0.0 || self.right != 0.0 || self.up != 0.0 || self.look != Vec2::ZERO
    }
}

impl FlyCamera {
    /// The camera of `transform` (its roll dropped: a walkthrough keeps the horizon
    /// level), flying at `speed` metres per second.
    pub fn from_transform(transform: &Transform, speed: f32) -> Self {
        let forward = transform.rotation * -Vec3::Z;
        let pitch = forward
            .y
            .clamp(-1.0, 1.0)
            .asin()
            .clamp(-MAX_PITCH, MAX_PITCH);
        let yaw = (-forward.x).atan2(-forward.z);
        Self {
            position: transform.translation,
            yaw,
            pitch,
            speed,
        }
    }

    /// The camera's orientation: yaw about +Y, then pitch about the camera's x axis.
    pub fn rotation(&self) -> Quat {
        Quat::from_euler(EulerRot::YXZ, self.yaw, self.pitch, 0.0)
    }

    /// Where the camera stands and looks, as a [`Transform`].
    pub fn transform(&self) -> Transform {
        Transform {
            translation: self.position,
            rotation: self.rotation(),
            scale: Vec3::ONE,
        }
    }

    /// Applies `input` held for `seconds`; returns whether the camera moved or turned.
    pub fn step(&mut self, input: &FlyInput, seconds: f32) -> bool {
        if input.speed_steps.is_finite() && input.speed_steps != 0.0 {
            self.speed = (self.speed * SPEED_STEP.powf(input.speed_steps)).clamp(0.01, 1.0e5);
        }
        if !input.moves() || !seconds.is_finite() || seconds <= 0.0 {
            return false;
        }
        self.yaw -= input.look.x;
        self.pitch = (self.pitch + input.look.y).clamp(-MAX_PITCH, MAX_PITCH);
        // Keys move along the ground's heading, as walking does; up and down are world Y.
        let heading = Quat::from_rotation_y(self.yaw);
        let (ahead, right) = (heading * -Vec3::Z, heading * Vec3::X);
        let clamp = |v: f32| v.clamp(-1.0, 1.0);
        let travel =
            ahead * clamp(input.forward) + right * clamp(input.right) + Vec3::Y * clamp(input.up);
        self.position += travel * self.speed * seconds;
        true
    }
}

/// A pose that looks down at 45° from the +Z side on the ground rectangle `min`..`max`
/// (x, z) at height `ground`, far enough back that the rectangle fits a view of
/// `vertical_fov` radians at `aspect` (width / height): the viewer's overview.
pub fn overview_pose(
    min: Vec2,
    max: Vec2,
    ground: f32,
    vertical_fov: f32,
    aspect: f32,
) -> Transform {
    let centre = Vec3::new(0.5 * (min.x + max.x), ground, 0.5 * (min.y + max.y));
    let radius = (0.5 * (max - min).length()).max(1.0);
    let half_fov = (0.5 * vertical_fov).min(((0.5 * vertical_fov).tan() * aspect).atan());
    let distance = radius / half_fov.sin().max(1e-3);
    let eye = centre + Vec3::new(0.0, 1.0, 1.0).normalize() * distance;
    Transform::looking_at(eye, centre, Vec3::Y)
}

/// One stop of a scripted walkthrough: where to stand, how long to refine, what to save.
#[derive(Clone, Debug, Default, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct ScriptStep {
    /// Load this scene (a scene file, preset name or glTF file) in place of the shown
    /// one, keeping the camera where it is; one that fails to load leaves the shown one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub open: Option<std::path::PathBuf>,
    /// Load the shown scene again (after its file changed), as F5 does.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub reload: bool,
    /// Where the camera moves to (it keeps its orientation without `look_at`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub position: Option<[f32; 3]>,
    /// The camera's exact orientation, a unit quaternion `[x, y, z, w]` (what `--record`
    /// writes); `look_at` takes precedence.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rotation: Option<[f32; 4]>,
    /// The point the camera turns to.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub look_at: Option<[f32; 3]>,
    /// First jump to the overview (`true`) or back to the scene's camera (`false`), as
    /// the viewer's V key does; the keys above then apply from there.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub overview: Option<bool>,
    /// Then walk this many metres along the camera's heading (level, as the keys do).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub advance: Option<f32>,
    /// Wait until the shown image holds this many accumulated frames (default 1).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames: Option<u32>,
    /// Select the plant seen at this pixel (`[x, y]` from the top-left corner).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub select: Option<[u32; 2]>,
    /// Select the plant whose crown covers this ground position `[x, z]` (the map's
    /// click), the one whose stem is nearest.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_select: Option<[f32; 2]>,
    /// Delete the selected plant.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub delete: bool,
    /// Plant one of the selected plant's species (or of the first species) where this
    /// pixel meets the ground or a plant.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub insert: Option<[u32; 2]>,
    /// Plant as `insert` does, at this ground position `[x, z]`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_insert: Option<[f32; 2]>,
    /// Move the selected plant to where this pixel meets the ground or a plant.
    #[serde(rename = "move", skip_serializing_if = "Option::is_none")]
    pub move_to: Option<[u32; 2]>,
    /// Move the selected plant to this ground position `[x, z]`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_move: Option<[f32; 2]>,
    /// Take back the latest edit.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub undo: bool,
    /// Make the latest undone edit again.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub redo: bool,
    /// Turn the wind on or off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub wind: Option<bool>,
    /// Save the edited ecosystem as a scene file here (after this step's edits).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub save: Option<std::path::PathBuf>,
    /// Hold a movement key for `seconds` (default 2), as a user does: `w`, `a`, `s`,
    /// `d` (forward, left, back, right), `q`, `e` (down, up) or an arrow (`up`, `down`,
    /// `left`, `right`); the camera flies at the window's speed meanwhile and the frames
    /// shown are counted (the walkthrough benchmark's continuous motion).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hold: Option<String>,
    /// How long `hold` holds its key, in seconds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f32>,
    /// Save the shown image (PNG) once the frames are there.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub screenshot: Option<std::path::PathBuf>,
    /// End the walkthrough after this step.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub quit: bool,
}

/// The keys a script's `hold` step can hold: the window's movement keys.
pub const HOLDABLE_KEYS: [&str; 10] = ["w", "a", "s", "d", "q", "e", "up", "down", "left", "right"];

/// A scripted walkthrough: steps run in order, each after the previous one's frames.
#[derive(Clone, Debug, Default, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct WalkthroughScript {
    /// The stops.
    #[serde(default, rename = "step")]
    pub steps: Vec<ScriptStep>,
}

impl WalkthroughScript {
    /// Parses a script's TOML (`[[step]]` tables); errors name the line and the key.
    pub fn parse(text: &str) -> Result<Self, String> {
        let script: Self = toml::from_str(text).map_err(|e| e.to_string())?;
        for (i, step) in script.steps.iter().enumerate() {
            let finite = |v: Option<&[f32]>| v.is_none_or(|v| v.iter().all(|c| c.is_finite()));
            if !finite(step.position.as_ref().map(|v| &v[..]))
                || !finite(step.look_at.as_ref().map(|v| &v[..]))
                || !finite(step.rotation.as_ref().map(|v| &v[..]))
                || [step.map_select, step.map_insert, step.map_move]
                    .iter()
                    .any(|v| !finite(v.as_ref().map(|v| &v[..])))
                || step.advance.is_some_and(|a| !a.is_finite())
            {
                return Err(format!(
                    "step {}: coordinates must be finite numbers",
                    i + 1
                ));
            }
            if let Some(q) = step.rotation
                && (Quat::from_array(q).length() - 1.0).abs() > 1e-3
            {
                return Err(format!(
                    "step {}: rotation must be a unit quaternion [x, y, z, w]",
                    i + 1
                ));
            }
            if step.frames == Some(0) {
                return Err(format!("step {}: frames must be at least 1", i + 1));
            }
            if let Some(key) = &step.hold
                && !HOLDABLE_KEYS.contains(&key.as_str())
            {
                return Err(format!(
                    "step {}: hold = {key:?} is not a movement key (expected one of {})",
                    i + 1,
                    HOLDABLE_KEYS.join(", ")
                ));
            }
            match (&step.hold, step.seconds) {
                (None, Some(_)) => {
                    return Err(format!("step {}: seconds goes with hold", i + 1));
                }
                (_, Some(t)) if !(t > 0.0 && t <= 600.0) => {
                    return Err(format!(
                        "step {}: seconds must be in (0, 600], not {t}",
                        i + 1
                    ));
                }
                _ => {}
            }
        }
        Ok(script)
    }

    /// The camera transform step `step` asks for, starting from `current`: moved to its
    /// position, turned to its `look_at` (unchanged where it says nothing).
    pub fn pose(step: &ScriptStep, current: &Transform) -> Transform {
        let eye = step.position.map_or(current.translation, Vec3::from);
        let mut pose = match step.look_at.map(Vec3::from) {
            Some(target) if (target - eye).length_squared() > 0.0 => {
                Transform::looking_at(eye, target, Vec3::Y)
            }
            _ => Transform {
                translation: eye,
                rotation: step.rotation.map_or(current.rotation, Quat::from_array),
                ..*current
            },
        };
        if let Some(metres) = step.advance {
            let forward = pose.rotation * -Vec3::Z;
            let heading = Vec3::new(forward.x, 0.0, forward.z).normalize_or_zero();
            pose.translation += heading * metres;
        }
        pose
    }

    /// True when `step` moves or turns the camera.
    pub fn moves(step: &ScriptStep) -> bool {
        step.position.is_some()
            || step.rotation.is_some()
            || step.look_at.is_some()
            || step.overview.is_some()
            || step.advance.is_some()
    }

    /// The script as TOML `[[step]]` tables, which [`parse`](Self::parse) reads back to
    /// the same steps.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("a script's keys and values all have TOML forms")
    }
}

/// Writes what a user does in the viewer as a [`WalkthroughScript`] (`sylva view
/// --record`): each step is an edit, a save, a screenshot, a quit or a camera rest, with
/// the exact camera pose when it changed since the last step, and the frames the user
/// watched before the next step (so a replay refines as far).
#[derive(Clone, Debug, Default)]
pub struct ScriptRecorder {
    steps: Vec<ScriptStep>,
    /// The pose of the latest step that set one, as its bits.
    pose: Option<([f32; 3], [f32; 4])>,
}

impl ScriptRecorder {
    /// Records `step` (its pose keys are ignored) made with the camera at `pose`, after
    /// the previous step was shown for `shown_frames` accumulated frames. A step that
    /// does nothing is recorded only when the camera has moved.
    pub fn record(&mut self, pose: &Transform, shown_frames: u32, step: ScriptStep) {
        let pose_bits = (pose.translation.to_array(), pose.rotation.to_array());
        let moved = self.pose != Some(pose_bits);
        let step = ScriptStep {
            position: moved.then_some(pose_bits.0),
            rotation: moved.then_some(pose_bits.1),
            look_at: None,
            overview: None,
            advance: None,
            frames: None,
            ..step
        };
        if step == ScriptStep::default() {
            return;
        }
        self.close(shown_frames);
        self.pose = Some(pose_bits);
        self.steps.push(step);
    }

    /// Sets the latest step's frames (kept only above the default of 1).
    fn close(&mut self, shown_frames: u32) {
        if let Some(last) = self.steps.last_mut() {
            last.frames = (shown_frames > 1).then_some(shown_frames);
        }
    }

    /// The walkthrough so far, its latest step shown for `shown_frames`.
    pub fn script(&self, shown_frames: u32) -> WalkthroughScript {
        let mut recorder = self.clone();
        recorder.close(shown_frames);
        WalkthroughScript {
            steps: recorder.steps,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_hold_step_names_a_movement_key_and_a_time() {
        let script = WalkthroughScript::parse("[[step]]\nhold = \"w\"\nseconds = 2.5\n").unwrap();
        assert_eq!(script.steps[0].hold.as_deref(), Some("w"));
        assert_eq!(script.steps[0].seconds, Some(2.5));
        let error = |text: &str| WalkthroughScript::parse(text).unwrap_err();
        assert!(error("[[step]]\nhold = \"x\"\n").contains("not a movement key"));
        assert!(error("[[step]]\nseconds = 1\n").contains("seconds goes with hold"));
        assert!(error("[[step]]\nhold = \"w\"\nseconds = 0\n").contains("seconds must be"));
    }

    fn close(a: Vec3, b: Vec3) -> bool {
        (a - b).length() < 1e-4
    }

    #[test]
    fn scripts_parse_and_bad_ones_say_where() {
        let script = WalkthroughScript::parse(
            "[[step]]\nposition = [0, 2, 10]\nlook_at = [0, 1, 0]\nframes = 4\nscreenshot = \"a.png\"\n\n[[step]]\nquit = true\n",
        )
        .unwrap();
        assert_eq!(script.steps.len(), 2);
        assert_eq!(script.steps[0].frames, Some(4));
        assert!(script.steps[1].quit);
        let pose = WalkthroughScript::pose(&script.steps[0], &Transform::IDENTITY);
        assert!(close(pose.translation, Vec3::new(0.0, 2.0, 10.0)));
        assert!(close(
            pose.rotation * -Vec3::Z,
            Vec3::new(0.0, -1.0, -10.0).normalize()
        ));
        let walk = WalkthroughScript::parse("[[step]]\nadvance = 3\n").unwrap();
        let ahead = WalkthroughScript::pose(&walk.steps[0], &pose);
        let level = Vec3::new(0.0, 0.0, -1.0) * 3.0;
        assert!(
            close(ahead.translation, pose.translation + level),
            "{}",
            ahead.translation
        );
        assert!(WalkthroughScript::moves(&walk.steps[0]));
        assert!(!WalkthroughScript::moves(&script.steps[1]));
        let unknown =
            WalkthroughScript::parse("[[step]]\nposition = [0, 2, 10]\nzoom = 2\n").unwrap_err();
        assert!(
            unknown.contains("zoom") && unknown.contains("line 3"),
            "{unknown}"
        );
        let zero = WalkthroughScript::parse("[[step]]\nframes = 0\n").unwrap_err();
        assert!(zero.contains("step 1"), "{zero}");
        let nan = WalkthroughScript::parse("[[step]]\nposition = [nan, 0, 0]\n").unwrap_err();
        assert!(nan.contains("finite"), "{nan}");
    }

    #[test]
    fn a_transform_comes_back_as_it_went_in_without_roll() {
        let eye = Vec3::new(3.0, 2.0, 5.0);
        for target in [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(10.0, 4.0, 5.0),
            Vec3::new(3.0, -1.0, 20.0),
        ] {
            let looking = Transform::looking_at(eye, target, Vec3::Y);
            let fly = FlyCamera::from_transform(&looking, 1.0);
            let back = fly.transform();
            assert!(close(back.translation, eye));
            let forward = (target - eye).normalize();
            assert!(close(back.rotation * -Vec3::Z, forward), "{target}");
            // The horizon stays level: the camera's x axis has no vertical part.
            assert!((back.rotation * Vec3::X).y.abs() < 1e-5);
        }
    }

    #[test]
    fn forward_moves_along_the_heading_at_the_speed_for_any_step_size() {
        let start = FlyCamera::from_transform(
            &Transform::looking_at(Vec3::ZERO, Vec3::new(1.0, 0.5, 0.0), Vec3::Y),
            4.0,
        );
        let input = FlyInput {
            forward: 1.0,
            ..FlyInput::default()
        };
        let (mut one, mut many) = (start, start);
        assert!(one.step(&input, 1.0));
        for _ in 0..10 {
            many.step(&input, 0.1);
        }
        // Along +X (the heading; the pitch does not lift the walk), 4 m in one second.
        assert!(
            close(one.position, Vec3::new(4.0, 0.0, 0.0)),
            "{}",
            one.position
        );
        assert!(close(many.position, one.position));
    }

    #[test]
    fn looking_turns_and_pitch_stops_short_of_straight_up() {
        let mut fly = FlyCamera::from_transform(&Transform::IDENTITY, 1.0);
        fly.step(
            &FlyInput {
                look: Vec2::new(std::f32::consts::FRAC_PI_2, 0.0),
                ..FlyInput::default()
            },
            0.016,
        );
        // A quarter turn right: looking along +X.
        assert!(close(fly.rotation() * -Vec3::Z, Vec3::X));
        fly.step(
            &FlyInput {
                look: Vec2::new(0.0, 10.0),
                ..FlyInput::default()
            },
            0.016,
        );
        assert_eq!(fly.pitch, MAX_PITCH);
    }

    #[test]
    fn scrolling_scales_the_speed_and_idle_input_does_not_move() {
        let mut fly = FlyCamera::from_transform(&Transform::IDENTITY, 2.0);
        let moved = fly.step(
            &FlyInput {
                speed_steps: 2.0,
                ..FlyInput::default()
            },
            0.5,
        );
        assert!(!moved);
        assert!((fly.speed - 2.0 * SPEED_STEP * SPEED_STEP).abs() < 1e-5);
        assert_eq!(fly.position, Vec3::ZERO);
        assert!(!fly.step(&FlyInput::default(), f32::NAN));
    }

    #[test]
    fn a_recording_keeps_exact_poses_and_frames_and_reads_back_as_written() {
        let start = Transform::looking_at(Vec3::new(1.0, 2.0, 3.0), Vec3::ZERO, Vec3::Y);
        let mut moved = start;
        moved.translation += Vec3::new(0.1, 0.0, -0.3);
        let mut recorder = ScriptRecorder::default();
        // A rest where the camera started, watched for 12 frames; an edit there; a rest
        // that did not move is not a step; then a move, a map edit and a quit.
        recorder.record(&start, 1, ScriptStep::default());
        recorder.record(
            &start,
            12,
            ScriptStep {
                select: Some([10, 20]),
                delete: true,
                ..ScriptStep::default()
            },
        );
        recorder.record(&start, 3, ScriptStep::default());
        recorder.record(
            &moved,
            5,
            ScriptStep {
                map_insert: Some([4.5, -2.25]),
                ..ScriptStep::default()
            },
        );
        recorder.record(
            &moved,
            7,
            ScriptStep {
                quit: true,
                ..ScriptStep::default()
            },
        );
        let script = recorder.script(1);
        let steps = &script.steps;
        assert_eq!(steps.len(), 4, "{steps:?}");
        assert_eq!(steps[0].position, Some(start.translation.to_array()));
        assert_eq!(steps[0].rotation, Some(start.rotation.to_array()));
        assert_eq!(steps[0].frames, Some(12));
        assert_eq!((steps[1].position, steps[1].frames), (None, Some(5)));
        assert!(steps[1].delete && steps[1].select == Some([10, 20]));
        assert_eq!(steps[2].position, Some(moved.translation.to_array()));
        assert_eq!(steps[2].frames, Some(7));
        assert!(steps[3].quit && steps[3].frames.is_none() && steps[3].position.is_none());

        let text = script.to_toml();
        let back = WalkthroughScript::parse(&text).unwrap();
        assert_eq!(back, script, "{text}");
        // Replayed, the poses come back bit for bit.
        let pose = WalkthroughScript::pose(&back.steps[2], &Transform::IDENTITY);
        assert_eq!(pose.translation.to_array(), moved.translation.to_array());
        assert_eq!(pose.rotation.to_array(), moved.rotation.to_array());
        let skewed = WalkthroughScript::parse("[[step]]\nrotation = [0, 0, 0, 2]\n").unwrap_err();
        assert!(skewed.contains("unit quaternion"), "{skewed}");
    }

    #[test]
    fn the_overview_sees_every_corner_of_the_ground() {
        for (min, max, aspect) in [
            (
                Vec2::new(-100.0, -100.0),
                Vec2::new(100.0, 100.0),
                4.0 / 3.0,
            ),
            (Vec2::new(-20.0, 10.0), Vec2::new(20.0, 50.0), 0.5),
            (Vec2::new(3.0, 3.0), Vec2::new(3.0, 3.0), 1.0),
        ] {
            let fov = 50f32.to_radians();
            let pose = overview_pose(min, max, 2.0, fov, aspect);
            let forward = pose.rotation * -Vec3::Z;
            assert!(forward.y < -0.5, "looks down: {forward}");
            let (right, up) = (pose.rotation * Vec3::X, pose.rotation * Vec3::Y);
            for corner in [min, max, Vec2::new(min.x, max.y), Vec2::new(max.x, min.y)] {
                let to = Vec3::new(corner.x, 2.0, corner.y) - pose.translation;
                let depth = to.dot(forward);
                assert!(depth > 0.0);
                let tan_y = (0.5 * fov).tan();
                assert!(to.dot(up).abs() / depth <= tan_y, "{corner} above or below");
                assert!(
                    to.dot(right).abs() / depth <= tan_y * aspect,
                    "{corner} aside"
                );
            }
        }
    }
}

//! The window's state and what its input does: the camera, edits, scripts, saving, and
//! drawing the latest frame with the HUD and the map.

use super::map::MapView;
use super::scene::{Saving, ViewSettings, load_scene};
use super::*;

/// A script in progress: the next step to start, and the step waiting for its frames.
pub(super) struct ScriptRun {
    pub(super) steps: Vec<sylva::systems::walkthrough::ScriptStep>,
    pub(super) next: usize,
    /// The running step's index, the sequence number of its camera command and the
    /// frames it waits for.
    pub(super) waiting: Option<(usize, u64, u32)>,
    /// When the running step sent its commands.
    pub(super) started: Instant,
    /// Each finished step: its frames and the time they took to show.
    pub(super) finished: Vec<(u32, Duration)>,
    /// A `hold` step in progress: its index, the key held and when it comes up.
    pub(super) holding: Option<(usize, KeyCode, Instant)>,
    /// What the `hold` steps saw: frames shown while a key was held, for how long, and
    /// the input-to-image latency of each of those frames that showed new input.
    pub(super) held: HeldKeys,
}

/// What a script's held keys saw (the walkthrough benchmark's continuous motion).
#[derive(Default)]
pub(super) struct HeldKeys {
    pub(super) frames: u32,
    pub(super) seconds: f64,
    pub(super) latencies: Vec<Duration>,
    /// The newest command a frame shown while holding reflected.
    pub(super) applied: u64,
}

/// The window's key for a script's `hold` name (one of `walkthrough::HOLDABLE_KEYS`).
pub(super) fn holdable_key(name: &str) -> Option<KeyCode> {
    Some(match name {
        "w" => KeyCode::KeyW,
        "a" => KeyCode::KeyA,
        "s" => KeyCode::KeyS,
        "d" => KeyCode::KeyD,
        "q" => KeyCode::KeyQ,
        "e" => KeyCode::KeyE,
        "up" => KeyCode::ArrowUp,
        "down" => KeyCode::ArrowDown,
        "left" => KeyCode::ArrowLeft,
        "right" => KeyCode::ArrowRight,
        _ => return None,
    })
}

pub(super) struct App {
    pub(super) live: LiveRender,
    /// Images shown a second and input-to-image latency, for the HUD.
    pub(super) responsiveness: Responsiveness,
    pub(super) saving: Arc<Saving>,
    /// The heads-up display (H toggles it).
    pub(super) hud: Option<Hud>,
    pub(super) hud_hidden: bool,
    /// The wind is blowing (G toggles it).
    pub(super) wind: bool,
    /// The top-down map panel is shown (Tab toggles it).
    pub(super) map_shown: bool,
    /// The camera entity (for picking on the render thread).
    pub(super) camera: Entity,
    pub(super) modifiers: Modifiers,
    /// Where the left button went down: a release nearby is a click, not a drag.
    pub(super) press: Option<PhysicalPosition<f64>>,
    pub(super) label: String,
    pub(super) size: (u32, u32),
    pub(super) window: Option<Rc<Window>>,
    pub(super) surface: Option<softbuffer::Surface<Rc<Window>, Rc<Window>>>,
    pub(super) shown: Option<ShownImage>,
    pub(super) fly: FlyCamera,
    pub(super) held: HashSet<KeyCode>,
    pub(super) look: glam::Vec2,
    pub(super) scroll: f32,
    pub(super) dragging: bool,
    pub(super) cursor: Option<PhysicalPosition<f64>>,
    pub(super) last_step: Instant,
    pub(super) script: Option<ScriptRun>,
    pub(super) screenshots: u32,
    pub(super) error: Option<anyhow::Error>,
    /// The camera pose last sent to the renderer.
    pub(super) pose: Transform,
    /// The scene shown (F5 loads it again; a script's `open` another).
    pub(super) scene: SceneArgs,
    pub(super) settings: Arc<ViewSettings>,
    /// The last load's failure, shown on the HUD and in the title until the next load.
    pub(super) status: Option<String>,
    /// The scene's camera and the overview, which V switches between.
    pub(super) views: [Transform; 2],
    /// The one shown last.
    pub(super) view: usize,
    /// I is held down (painting plants): where the cursor was at the last insert.
    pub(super) brush: Option<PhysicalPosition<f64>>,
    /// The camera moved at the last step (its coming to rest is recorded).
    pub(super) moving: bool,
    /// `--record`: where the walkthrough goes, and what it holds so far.
    pub(super) recorder: Option<(PathBuf, ScriptRecorder)>,
    /// `--frames-out`: the writer of every shown frame.
    pub(super) frames_out: Option<FrameWriter>,
    /// Every rank of an MPI run renders (`--cluster`): the scene cannot be switched.
    pub(super) clustered: bool,
}

/// Pixels the cursor moves between two of the brush's inserts.
pub(super) const BRUSH_STEP: f64 = 8.0;

/// Radians of turn per pixel of mouse drag.
pub(super) const LOOK_PER_PIXEL: f32 = 0.004;

impl App {
    /// Sends an editor action the user made (recorded with `--record`); its sequence
    /// number.
    pub(super) fn edit(&mut self, action: EditorAction) -> Option<u64> {
        let step = match action {
            EditorAction::Select(x, y) => ScriptStep {
                select: Some([x, y]),
                ..ScriptStep::default()
            },
            EditorAction::Insert(x, y) => ScriptStep {
                insert: Some([x, y]),
                ..ScriptStep::default()
            },
            EditorAction::Move(x, y) => ScriptStep {
                move_to: Some([x, y]),
                ..ScriptStep::default()
            },
            EditorAction::Delete => ScriptStep {
                delete: true,
                ..ScriptStep::default()
            },
            EditorAction::Undo => ScriptStep {
                undo: true,
                ..ScriptStep::default()
            },
            EditorAction::Redo => ScriptStep {
                redo: true,
                ..ScriptStep::default()
            },
            EditorAction::Wind(on) => ScriptStep {
                wind: Some(on),
                ..ScriptStep::default()
            },
            EditorAction::SelectAtGround(x, z) => ScriptStep {
                map_select: Some([x, z]),
                ..ScriptStep::default()
            },
            EditorAction::SelectPlant(plant) => ScriptStep {
                map_select: self
                    .shown
                    .as_ref()
                    .and_then(|s| s.map.iter().find(|p| p.entity == plant))
                    .map(|p| p.position.to_array()),
                ..ScriptStep::default()
            },
            EditorAction::InsertAtGround(x, z) => ScriptStep {
                map_insert: Some([x, z]),
                ..ScriptStep::default()
            },
            EditorAction::MoveToGround(x, z) => ScriptStep {
                map_move: Some([x, z]),
                ..ScriptStep::default()
            },
        };
        self.record(step);
        self.send(LiveCommand::Shared(action.to_bytes()))
    }

    /// Records `step` with `--record`, at the pose last sent.
    pub(super) fn record(&mut self, step: ScriptStep) {
        let shown_frames = self.shown.as_ref().map_or(1, |s| s.frames);
        if let Some((_, recorder)) = &mut self.recorder {
            recorder.record(&self.pose, shown_frames, step);
        }
    }

    /// Loads `scene` in place of the one shown, keeping the camera where it is; a scene
    /// that fails to load leaves the shown one running and its error on the HUD.
    /// Returns the sequence number a step waits for.
    pub(super) fn switch_scene(&mut self, scene: SceneArgs) -> u64 {
        if self.clustered {
            let message = format!(
                "{}: switching scenes is not available with --cluster (kept {})",
                scene_label(&scene),
                self.label
            );
            eprintln!("error: {message}");
            self.status = Some(message);
            self.update_title();
            return self.live.last_sent();
        }
        let loaded = match load_scene(&self.settings, &scene, (Some(self.size.0), self.size.1)) {
            Ok(loaded) => loaded,
            Err(e) => {
                let message = format!("{}: {e:#} (kept {})", scene_label(&scene), self.label);
                eprintln!("error: {message}");
                self.status = Some(message);
                self.update_title();
                return self.live.last_sent();
            }
        };
        self.live = loaded.live;
        self.camera = loaded.facts.camera;
        self.views = [loaded.facts.start_pose, loaded.facts.overview];
        self.saving = Arc::new(loaded.facts.saving);
        self.label = loaded.facts.label;
        if let Some(hud) = &mut self.hud {
            hud.triangles = loaded.facts.triangles;
        }
        self.scene = scene;
        self.status = None;
        self.wind = false;
        // The image shown came from the last render thread: the next frames must come
        // from this one before a script step counts them.
        if let Some(shown) = &mut self.shown {
            (shown.applied, shown.frames) = (0, 0);
        }
        eprintln!("loaded {}", self.label);
        self.send_pose(self.pose).unwrap_or(0)
    }

    /// Plants one of the selected plant's species where the cursor points, on the map or
    /// in the view (refused by the render thread where the layer's spacing forbids it).
    pub(super) fn insert_at_cursor(&mut self) {
        if let Some(at) = self.cursor_on_map() {
            self.edit(EditorAction::InsertAtGround(at.x, at.y));
        } else if let Some((x, y)) = self.cursor_pixel() {
            self.edit(EditorAction::Insert(x, y));
        }
    }

    /// Records the end of the walkthrough (a script's own quit step is recorded with it).
    pub(super) fn record_quit(&mut self) {
        self.record(ScriptStep {
            quit: true,
            ..ScriptStep::default()
        });
    }

    /// Sends a camera pose; its sequence number.
    pub(super) fn send_pose(&mut self, pose: Transform) -> Option<u64> {
        self.pose = pose;
        self.send(LiveCommand::Pose(pose))
    }

    /// Sends a command to the render thread, noting when (the HUD's latency); its
    /// sequence number.
    pub(super) fn send(&mut self, command: LiveCommand) -> Option<u64> {
        let number = self.live.send(command)?;
        self.responsiveness.sent(number, Instant::now());
        Some(number)
    }

    /// The map panel as drawn now, when it is shown.
    pub(super) fn map_view(&self) -> Option<MapView> {
        let shown = self.shown.as_ref().filter(|_| self.map_shown)?;
        Some(MapView::new(self.size.0, self.size.1, &shown.map))
    }

    /// The ground position (x, z) under the cursor when it is over the map panel.
    pub(super) fn cursor_on_map(&self) -> Option<glam::Vec2> {
        let (map, cursor) = self.map_view().zip(self.cursor)?;
        let (x, y) = (cursor.x as f32, cursor.y as f32);
        map.contains(x, y).then(|| map.to_world(x, y))
    }

    /// The image pixel under the cursor, if it is over the image.
    pub(super) fn cursor_pixel(&self) -> Option<(u32, u32)> {
        let cursor = self.cursor?;
        let (x, y) = (cursor.x.floor(), cursor.y.floor());
        (x >= 0.0 && y >= 0.0 && (x as u32) < self.size.0 && (y as u32) < self.size.1)
            .then_some((x as u32, y as u32))
    }

    pub(super) fn fail(&mut self, event_loop: &ActiveEventLoop, error: anyhow::Error) {
        self.error = Some(error);
        event_loop.exit();
    }

    /// What the held keys ask for.
    pub(super) fn input(&self) -> FlyInput {
        let axis = |plus: &[KeyCode], minus: &[KeyCode]| {
            let on = |keys: &[KeyCode]| keys.iter().any(|k| self.held.contains(k));
            f32::from(u8::from(on(plus))) - f32::from(u8::from(on(minus)))
        };
        FlyInput {
            forward: axis(
                &[KeyCode::KeyW, KeyCode::ArrowUp],
                &[KeyCode::KeyS, KeyCode::ArrowDown],
            ),
            right: axis(
                &[KeyCode::KeyD, KeyCode::ArrowRight],
                &[KeyCode::KeyA, KeyCode::ArrowLeft],
            ),
            up: axis(
                &[KeyCode::KeyE, KeyCode::Space],
                &[KeyCode::KeyQ, KeyCode::KeyC],
            ),
            look: self.look,
            speed_steps: self.scroll,
        }
    }

    /// The window title as a heads-up line: frames, frame time, rays/s, speed, keys.
    pub(super) fn update_title(&self) {
        let (Some(window), Some(shown)) = (&self.window, &self.shown) else {
            return;
        };
        if let Some(status) = &self.status {
            window.set_title(&format!("sylva view: load failed: {status}"));
            return;
        }
        window.set_title(&format!(
            "sylva view: {}, {} frames, {:.0} ms/frame, {:.2} M rays/s, {:.1} m/s, {} (WASD/arrows move, Q/E down/up, drag to look, scroll speed, click select, I insert (hold and move to paint), M move, Del delete, Ctrl+Z/Y undo/redo, G wind, V overview/camera, F5 reload, Tab map, H HUD, P screenshot, Esc quit)",
            self.label,
            shown.frames,
            shown.frame_time.as_secs_f64() * 1e3,
            shown.rays_per_second / 1e6,
            self.fly.speed,
            shown
                .selected
                .map_or("nothing selected".to_string(), |e| format!("plant {e} selected")),
        ));
    }

    /// Saves the shown frame as a PNG (atomically) with what it shows in its metadata.
    pub(super) fn screenshot(&mut self, path: &Path) -> Result<()> {
        let shown = self
            .shown
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("no frame to save yet"))?;
        let rgba: Vec<u8> = shown
            .pixels
            .iter()
            .flat_map(|p| [(p >> 16) as u8, (p >> 8) as u8, *p as u8, 255])
            .collect();
        let pose = self.fly.transform();
        let forward = pose.rotation * -glam::Vec3::Z;
        let metadata: Vec<(String, String)> = [
            (
                "Software",
                format!("sylva {} view", env!("CARGO_PKG_VERSION")),
            ),
            ("sylva.scene", self.label.clone()),
            ("sylva.size", format!("{}x{}", shown.width, shown.height)),
            ("sylva.frames", shown.frames.to_string()),
            ("sylva.quality", "interactive".to_string()),
            (
                "sylva.camera.position",
                format!("{:?}", pose.translation.to_array()),
            ),
            ("sylva.camera.forward", format!("{:?}", forward.to_array())),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        sylva::engine::film::write_rgba8_png(path, (shown.width, shown.height), &rgba, &metadata)?;
        eprintln!("saved {}", path.display());
        Ok(())
    }

    /// Lets go of a script's held key once its time is up; the step then waits for its
    /// frames at the pose the walk reached.
    pub(super) fn end_hold(&mut self, event_loop: &ActiveEventLoop, now: Instant) {
        let Some(script) = &mut self.script else {
            return;
        };
        let Some((index, key, until)) = script.holding else {
            return;
        };
        if now < until {
            return;
        }
        script.holding = None;
        let frames = script.steps[index].frames.unwrap_or(1);
        self.held.remove(&key);
        // The last pose the walk sent: the step waits for a frame that shows it.
        let command = self.live.last_sent();
        if let Some(script) = &mut self.script {
            script.waiting = Some((index, command, frames));
            script.started = now;
        }
        self.advance_script(event_loop);
    }

    /// Counts a frame shown while a script holds a key (and its latency when it shows
    /// new input).
    pub(super) fn note_held_frame(&mut self, applied: u64) {
        let latency = self.responsiveness.latency();
        let Some(script) = self.script.as_mut().filter(|s| s.holding.is_some()) else {
            return;
        };
        script.held.frames += 1;
        if applied > script.held.applied {
            script.held.applied = applied;
            script.held.latencies.extend(latency);
        }
    }

    /// Starts the script's next step, or finishes a step whose frames are shown.
    pub(super) fn advance_script(&mut self, event_loop: &ActiveEventLoop) {
        loop {
            let Some(script) = &mut self.script else {
                return;
            };
            if script.holding.is_some() {
                // A held key comes up in `end_hold`, on the event loop's clock.
                return;
            }
            match script.waiting {
                Some((index, command, frames)) => {
                    let Some(shown) = &self.shown else { return };
                    if shown.applied < command || shown.frames < frames {
                        return;
                    }
                    let step = script.steps[index].clone();
                    script.waiting = None;
                    script.finished.push((frames, script.started.elapsed()));
                    if let Some(path) = &step.screenshot
                        && let Err(e) = self.screenshot(path)
                    {
                        return self.fail(event_loop, e);
                    }
                    if step.quit {
                        event_loop.exit();
                        return;
                    }
                }
                None => {
                    let Some(step) = script.steps.get(script.next).cloned() else {
                        return;
                    };
                    let index = script.next;
                    script.next += 1;
                    let opened = match (&step.open, step.reload) {
                        (Some(path), _) => {
                            let scene = self.scene.opening(path);
                            Some(self.switch_scene(scene))
                        }
                        (None, true) => Some(self.switch_scene(self.scene.clone())),
                        (None, false) => None,
                    };
                    // A step that stays where the camera is sends nothing: a pose that
                    // differs in the last bit would restart the accumulation.
                    let command = if WalkthroughScript::moves(&step) {
                        let from = match step.overview {
                            Some(overview) => {
                                self.view = usize::from(overview);
                                self.views[self.view]
                            }
                            None => self.pose,
                        };
                        let pose = WalkthroughScript::pose(&step, &from);
                        self.fly = FlyCamera::from_transform(&pose, self.fly.speed);
                        let Some(command) = self.send_pose(pose) else {
                            return self.fail(event_loop, anyhow::anyhow!("the renderer stopped"));
                        };
                        command
                    } else {
                        opened.unwrap_or_else(|| self.live.last_sent())
                    };
                    self.record(step.clone());
                    let actions = [
                        step.select.map(|[x, y]| EditorAction::Select(x, y)),
                        step.map_select
                            .map(|[x, z]| EditorAction::SelectAtGround(x, z)),
                        step.insert.map(|[x, y]| EditorAction::Insert(x, y)),
                        step.map_insert
                            .map(|[x, z]| EditorAction::InsertAtGround(x, z)),
                        step.move_to.map(|[x, y]| EditorAction::Move(x, y)),
                        step.map_move.map(|[x, z]| EditorAction::MoveToGround(x, z)),
                        step.delete.then_some(EditorAction::Delete),
                        step.undo.then_some(EditorAction::Undo),
                        step.redo.then_some(EditorAction::Redo),
                        step.wind.map(EditorAction::Wind),
                    ];
                    let mut command = command;
                    for action in actions.into_iter().flatten() {
                        let Some(number) = self.send(LiveCommand::Shared(action.to_bytes())) else {
                            return self.fail(event_loop, anyhow::anyhow!("the renderer stopped"));
                        };
                        command = number;
                    }
                    if let Some(path) = &step.save {
                        let Some(number) = self.send(self.saving.command(Some(path.clone())))
                        else {
                            return self.fail(event_loop, anyhow::anyhow!("the renderer stopped"));
                        };
                        command = number;
                    }
                    if let Some(name) = &step.hold {
                        let Some(key) = holdable_key(name) else {
                            return self.fail(
                                event_loop,
                                anyhow::anyhow!(
                                    "step {}: hold = {name:?} is not a movement key",
                                    index + 1
                                ),
                            );
                        };
                        self.held.insert(key);
                        let seconds = step.seconds.unwrap_or(2.0);
                        if let Some(script) = &mut self.script {
                            script.holding = Some((
                                index,
                                key,
                                Instant::now() + Duration::from_secs_f32(seconds),
                            ));
                            script.held.seconds += f64::from(seconds);
                            script.held.applied = self.live.last_sent();
                        }
                        return;
                    }
                    if let Some(script) = &mut self.script {
                        script.waiting = Some((index, command, step.frames.unwrap_or(1)));
                        script.started = Instant::now();
                    }
                }
            }
        }
    }
}

impl App {
    /// Copies the latest frame into the window (black where the window is larger).
    pub(super) fn present(&mut self) -> Result<()> {
        let map = self.map_view();
        let (Some(window), Some(surface)) = (&self.window, &mut self.surface) else {
            return Ok(());
        };
        let size = window.inner_size();
        let (Some(w), Some(h)) = (NonZeroU32::new(size.width), NonZeroU32::new(size.height)) else {
            return Ok(());
        };
        surface
            .resize(w, h)
            .map_err(|e| anyhow::anyhow!("cannot size the window's buffer: {e}"))?;
        let mut buffer = surface
            .buffer_mut()
            .map_err(|e| anyhow::anyhow!("cannot draw to the window: {e}"))?;
        buffer.fill(0);
        if let Some(shown) = &self.shown {
            let columns = (shown.width as usize).min(size.width as usize);
            for row in 0..(shown.height as usize).min(size.height as usize) {
                let src = row * shown.width as usize;
                let dst = row * size.width as usize;
                buffer[dst..dst + columns].copy_from_slice(&shown.pixels[src..src + columns]);
            }
            if let Some(map) = map {
                map.draw(&mut buffer, size.width as usize, &shown.map, shown.selected);
            }
            if let Some(hud) = self.hud.as_ref().filter(|_| !self.hud_hidden) {
                let mut lines = hud.lines(shown, self.fly.speed, &self.responsiveness);
                if let Some(status) = &self.status {
                    lines.push(format!("load failed: {status}"));
                }
                hud.draw(
                    &mut buffer,
                    size.width as usize,
                    size.height as usize,
                    &lines,
                );
            }
        }
        buffer
            .present()
            .map_err(|e| anyhow::anyhow!("cannot show the frame: {e}"))?;
        Ok(())
    }
}

//! winit's events turned into the app's actions: keys, mouse, resizes, redraws and the
//! render thread's frames.

use super::app::{BRUSH_STEP, LOOK_PER_PIXEL};
use super::*;

impl ApplicationHandler<FrameReady> for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.window.is_some() {
            return;
        }
        let attributes = Window::default_attributes()
            .with_title(format!("sylva view: {}", self.label))
            .with_inner_size(PhysicalSize::new(self.size.0, self.size.1))
            .with_resizable(false);
        let window = match event_loop.create_window(attributes) {
            Ok(window) => Rc::new(window),
            Err(e) => return self.fail(event_loop, anyhow::anyhow!("cannot open a window: {e}")),
        };
        let surface = softbuffer::Context::new(window.clone())
            .and_then(|context| softbuffer::Surface::new(&context, window.clone()));
        match surface {
            Ok(surface) => self.surface = Some(surface),
            Err(e) => {
                return self.fail(
                    event_loop,
                    anyhow::anyhow!("cannot draw to the window: {e}"),
                );
            }
        }
        self.window = Some(window);
    }

    fn user_event(&mut self, event_loop: &ActiveEventLoop, _: FrameReady) {
        if let Some(failure) = self.live.failure() {
            return self.fail(
                event_loop,
                anyhow::anyhow!("the render thread failed: {failure}"),
            );
        }
        if let Some(image) = self.live.take_latest() {
            self.responsiveness.shown(image.applied, Instant::now());
            self.note_held_frame(image.applied);
            if let Some(writer) = &self.frames_out
                && !writer.push(&image)
            {
                self.frames_out.take();
                return self.fail(
                    event_loop,
                    anyhow::anyhow!("saving the shown frames failed"),
                );
            }
            self.shown = Some(image);
            self.update_title();
            if let Some(window) = &self.window {
                window.request_redraw();
            }
            self.advance_script(event_loop);
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => {
                self.record_quit();
                event_loop.exit();
            }
            WindowEvent::KeyboardInput { event, .. } => {
                let PhysicalKey::Code(code) = event.physical_key else {
                    return;
                };
                match (code, event.state) {
                    (KeyCode::Escape, ElementState::Pressed) => {
                        self.record_quit();
                        event_loop.exit();
                    }
                    (KeyCode::Delete | KeyCode::Backspace, ElementState::Pressed)
                        if !event.repeat =>
                    {
                        self.edit(EditorAction::Delete);
                    }
                    (KeyCode::KeyI, ElementState::Pressed) if !event.repeat => {
                        self.brush = self.cursor;
                        self.insert_at_cursor();
                    }
                    (KeyCode::KeyI, ElementState::Released) => self.brush = None,
                    (KeyCode::KeyM, ElementState::Pressed) if !event.repeat => {
                        if let Some((x, y)) = self.cursor_pixel() {
                            self.edit(EditorAction::Move(x, y));
                        }
                    }
                    (KeyCode::KeyS, ElementState::Pressed)
                        if self.modifiers.state().control_key() && !event.repeat =>
                    {
                        self.held.remove(&KeyCode::KeyS);
                        self.record(ScriptStep {
                            save: Some(self.saving.path.clone()),
                            ..ScriptStep::default()
                        });
                        self.send(self.saving.command(None));
                    }
                    (KeyCode::KeyZ | KeyCode::KeyY, ElementState::Pressed)
                        if self.modifiers.state().control_key() =>
                    {
                        let redo = code == KeyCode::KeyY || self.modifiers.state().shift_key();
                        self.edit(if redo {
                            EditorAction::Redo
                        } else {
                            EditorAction::Undo
                        });
                    }
                    (KeyCode::Tab, ElementState::Pressed) if !event.repeat => {
                        self.map_shown = !self.map_shown;
                        if let Some(window) = &self.window {
                            window.request_redraw();
                        }
                    }
                    (KeyCode::KeyG, ElementState::Pressed) if !event.repeat => {
                        self.wind = !self.wind;
                        self.edit(EditorAction::Wind(self.wind));
                    }
                    (KeyCode::F5, ElementState::Pressed) if !event.repeat => {
                        self.switch_scene(self.scene.clone());
                        self.record(ScriptStep {
                            reload: true,
                            ..ScriptStep::default()
                        });
                    }
                    (KeyCode::KeyV, ElementState::Pressed) if !event.repeat => {
                        self.view = (self.view + 1) % self.views.len();
                        let pose = self.views[self.view];
                        self.fly = FlyCamera::from_transform(&pose, self.fly.speed);
                        if self.send_pose(pose).is_none() {
                            return self.fail(event_loop, anyhow::anyhow!("the renderer stopped"));
                        }
                        self.record(ScriptStep::default());
                    }
                    (KeyCode::KeyH, ElementState::Pressed) if !event.repeat => {
                        self.hud_hidden = !self.hud_hidden;
                        if let Some(window) = &self.window {
                            window.request_redraw();
                        }
                    }
                    (KeyCode::KeyP, ElementState::Pressed) if !event.repeat => {
                        self.screenshots += 1;
                        let path = PathBuf::from(format!("sylva-view-{:03}.png", self.screenshots));
                        if let Err(e) = self.screenshot(&path) {
                            eprintln!("warning: {e:#}");
                        } else {
                            self.record(ScriptStep {
                                screenshot: Some(path),
                                ..ScriptStep::default()
                            });
                        }
                    }
                    (code, ElementState::Pressed) => {
                        self.held.insert(code);
                    }
                    (code, ElementState::Released) => {
                        self.held.remove(&code);
                    }
                }
            }
            WindowEvent::Focused(false) => {
                self.held.clear();
                self.brush = None;
            }
            WindowEvent::ModifiersChanged(modifiers) => self.modifiers = modifiers,
            WindowEvent::MouseInput {
                state,
                button: MouseButton::Left,
                ..
            } => {
                self.dragging = state == ElementState::Pressed;
                match state {
                    ElementState::Pressed => self.press = self.cursor,
                    ElementState::Released => {
                        // A click (the cursor barely moved) selects what it points at.
                        let press = self.press.take();
                        let clicked = press
                            .zip(self.cursor)
                            .is_some_and(|(a, b)| (a.x - b.x).abs() + (a.y - b.y).abs() < 4.0);
                        let on_map = self
                            .map_view()
                            .zip(press)
                            .filter(|(map, p)| map.contains(p.x as f32, p.y as f32));
                        if let (Some((map, _)), Some(cursor)) = (on_map, self.cursor) {
                            // On the map a click selects and a drag moves the selection.
                            let (x, y) = (cursor.x as f32, cursor.y as f32);
                            if clicked {
                                let plants = self
                                    .shown
                                    .as_ref()
                                    .map(|s| s.map.clone())
                                    .unwrap_or_default();
                                if let Some(plant) = map.plant_at(&plants, x, y) {
                                    self.edit(EditorAction::SelectPlant(plant));
                                }
                            } else if map.contains(x, y) {
                                let to = map.to_world(x, y);
                                self.edit(EditorAction::MoveToGround(to.x, to.y));
                            }
                        } else if clicked && let Some((x, y)) = self.cursor_pixel() {
                            self.edit(EditorAction::Select(x, y));
                        }
                    }
                }
            }
            WindowEvent::CursorMoved { position, .. } => {
                let on_map = self
                    .map_view()
                    .zip(self.press)
                    .is_some_and(|(map, p)| map.contains(p.x as f32, p.y as f32));
                if self.dragging
                    && !on_map
                    && let Some(last) = self.cursor
                {
                    self.look += glam::Vec2::new(
                        (position.x - last.x) as f32,
                        -(position.y - last.y) as f32,
                    ) * LOOK_PER_PIXEL;
                }
                self.cursor = Some(position);
                // I held down paints: a plant wherever the cursor has moved on a few
                // pixels, where the layer's spacing allows one.
                if let Some(last) = self.brush
                    && (position.x - last.x).abs() + (position.y - last.y).abs() >= BRUSH_STEP
                {
                    self.brush = Some(position);
                    self.insert_at_cursor();
                }
            }
            WindowEvent::MouseWheel { delta, .. } => {
                self.scroll += match delta {
                    MouseScrollDelta::LineDelta(_, y) => y,
                    MouseScrollDelta::PixelDelta(p) => (p.y / 40.0) as f32,
                };
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.present() {
                    self.fail(event_loop, e);
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        let now = Instant::now();
        self.end_hold(event_loop, now);
        let seconds = now.duration_since(self.last_step).as_secs_f32().min(0.1);
        self.last_step = now;
        let input = self.input();
        (self.look, self.scroll) = (glam::Vec2::ZERO, 0.0);
        let scrolled = input.speed_steps != 0.0;
        if self.fly.step(&input, seconds) {
            self.moving = true;
            let pose = self.fly.transform();
            if self.send_pose(pose).is_none() {
                return self.fail(event_loop, anyhow::anyhow!("the renderer stopped"));
            }
        } else if std::mem::take(&mut self.moving) {
            // Come to rest: a stop of the recorded walkthrough.
            self.record(ScriptStep::default());
        }
        if scrolled {
            self.update_title();
        }
        // Keys held: keep stepping at about 60 Hz; otherwise sleep until an event.
        event_loop.set_control_flow(if self.held.is_empty() {
            ControlFlow::Wait
        } else {
            ControlFlow::WaitUntil(now + Duration::from_millis(16))
        });
    }
}

//! Loading a scene for the window: building it from a preset, scene file or glTF file,
//! what the window shows of it, and starting (or restarting) the render thread on it.

use super::*;

/// What every scene the window loads is set up with.
pub(super) struct ViewSettings {
    pub(super) env: Option<PathBuf>,
    pub(super) lights: u32,
    pub(super) exposure: f32,
    pub(super) max_frames: u32,
    pub(super) save: Option<PathBuf>,
    /// Wakes the event loop when the render thread has a frame (none on the ranks that
    /// only render).
    pub(super) wake: Option<winit::event_loop::EventLoopProxy<FrameReady>>,
    /// `--profile`: every shown frame of every scene opened is added to it.
    pub(super) profile: Option<Arc<Mutex<ProfileLog>>>,
}

/// What the window needs to know of the scene it shows.
pub(super) struct SceneFacts {
    pub(super) camera: Entity,
    pub(super) start_pose: Transform,
    pub(super) overview: Transform,
    pub(super) triangles: u64,
    pub(super) width: u32,
    /// A walking pace for the scene's size.
    pub(super) speed: f32,
    pub(super) saving: Saving,
    pub(super) label: String,
}

/// A scene built into a world, its render thread not yet started.
pub(super) struct BuiltScene {
    pub(super) world: World,
    pub(super) facts: SceneFacts,
}

/// A scene loaded into a world with its render thread running.
pub(super) struct LoadedScene {
    pub(super) live: LiveRender,
    pub(super) facts: SceneFacts,
}

/// Builds `scene` lit as `settings` say, sized `(width, height)`, and starts its render
/// thread.
pub(super) fn load_scene(
    settings: &ViewSettings,
    scene_args: &SceneArgs,
    size: (Option<u32>, u32),
) -> Result<LoadedScene> {
    start_scene(settings, build_scene(settings, scene_args, size)?, None)
}

/// Builds `scene` lit as `settings` say, sized `(width, height)`, at interactive quality;
/// its editor actions arrive as shared edits.
pub(super) fn build_scene(
    settings: &ViewSettings,
    scene_args: &SceneArgs,
    (width, height): (Option<u32>, u32),
) -> Result<BuiltScene> {
    let mut world = World::new();
    let (scene, width, environment) = build_framed(
        &mut world,
        scene_args,
        (settings.env.as_deref(), settings.lights),
        &Framing {
            size: (width, height),
            max_width: 8192,
            exposure: settings.exposure,
        },
    )?;
    let start_pose = scene.camera_transform;
    let overview = {
        use glam::Vec3Swizzles;
        let (mut min, mut max, mut ground) = (
            glam::Vec2::splat(f32::MAX),
            glam::Vec2::splat(f32::MIN),
            0.0f64,
        );
        for plant in &scene.plants {
            let t = plant.transform.translation;
            (min, max) = (min.min(t.xz()), max.max(t.xz()));
            ground += f64::from(t.y);
        }
        if scene.plants.is_empty() {
            (min, max) = (start_pose.translation.xz(), start_pose.translation.xz());
        }
        let ground = (ground / scene.plants.len().max(1) as f64) as f32;
        let aspect = width as f32 / height as f32;
        overview_pose(min, max, ground, scene.camera.vertical_fov, aspect)
    };
    let triangles = scene.stats().instanced_triangles;
    // A pace for the scene's size: a twentieth of the plants' spread per second.
    let extent = scene.plants.iter().fold(1.0f32, |m, p| {
        m.max(p.transform.translation.x.abs())
            .max(p.transform.translation.z.abs())
    });
    let spawned = spawn(&mut world, scene);
    if let Some(environment) = environment {
        world.spawn(environment);
    }
    Quality::interactive().apply(&mut world, spawned.camera);
    if settings.profile.is_some() {
        world.insert_resource(FrameProfiler::enabled());
    }
    let camera = spawned.camera;
    world.insert_resource(SharedEdits(Arc::new(
        move |world: &mut World, bytes: &[u8]| {
            editor::EditorAction::from_bytes(bytes)?.apply(world, camera);
            Ok(())
        },
    )));
    let saving = Saving {
        source: match (&scene_args.gltf, scene_args.scene.as_str()) {
            (Some(_), _) => None,
            (None, name) if name.ends_with(".toml") => {
                Some(editor::SceneSource::File(PathBuf::from(name)))
            }
            (None, name) => Some(editor::SceneSource::Preset(name.to_string())),
        },
        seed: scene_args.seed,
        path: settings.save.clone().unwrap_or_else(|| {
            let stem = Path::new(&scene_args.scene)
                .file_stem()
                .map_or("scene".into(), |s| s.to_string_lossy().into_owned());
            PathBuf::from(format!("{stem}-edited.toml"))
        }),
    };
    Ok(BuiltScene {
        world,
        facts: SceneFacts {
            camera,
            start_pose,
            overview,
            triangles,
            width,
            speed: (extent * 0.05).clamp(1.0, 200.0),
            saving,
            label: scene_label(scene_args),
        },
    })
}

/// Starts the render thread of a built scene; on rank 0 of a cluster run with its
/// `cluster`, which every frame is then shared out over.
pub(super) fn start_scene(
    settings: &ViewSettings,
    mut built: BuiltScene,
    cluster: Option<Cluster>,
) -> Result<LoadedScene> {
    if let Some(cluster) = cluster {
        built.world.insert_resource(cluster);
    }
    let wake = settings.wake.clone();
    let live = LiveRender::start_profiled(
        built.world,
        built.facts.camera,
        settings.max_frames,
        settings.profile.clone(),
        move || {
            if let Some(wake) = &wake {
                let _ = wake.send_event(FrameReady);
            }
        },
    )?;
    Ok(LoadedScene {
        live,
        facts: built.facts,
    })
}

/// What saving the edited ecosystem needs: where the scene came from, its seed and
/// where Ctrl+S writes.
pub(super) struct Saving {
    pub(super) source: Option<editor::SceneSource>,
    pub(super) seed: u64,
    pub(super) path: PathBuf,
}

impl Saving {
    /// The command that saves on the render thread to `path` (the default when `None`),
    /// reporting on standard error.
    pub(super) fn command(self: &Arc<Self>, path: Option<PathBuf>) -> LiveCommand {
        let saving = self.clone();
        LiveCommand::Edit(Arc::new(move |world: &mut World| {
            let path = path.clone().unwrap_or_else(|| saving.path.clone());
            let Some(source) = &saving.source else {
                eprintln!("error: saving needs a built-in scene or a .toml scene file, not glTF");
                return;
            };
            match editor::save_ecosystem(world, source, saving.seed, &path) {
                Ok(plants) => eprintln!("saved {plants} plants to {}", path.display()),
                Err(e) => eprintln!("error: {e}"),
            }
        }))
    }
}

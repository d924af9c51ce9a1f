//! An imported file as a scene: the camera chosen, species from its meshes, plants
//! from its instances, and the default light and framing when the file has none.

use super::*;

/// Which view to use.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum CameraChoice {
    /// The first perspective camera, or a framing view without one.
    #[default]
    First,
    /// A camera by name.
    Named(String),
    /// A camera by index among the perspective cameras.
    Index(usize),
}

impl CameraChoice {
    /// Parses `--camera`: a number is an index, anything else a name.
    pub fn parse(text: &str) -> Self {
        text.parse().map_or_else(
            |_| CameraChoice::Named(text.to_string()),
            CameraChoice::Index,
        )
    }
}

impl GltfScene {
    /// World bounds of every instance.
    pub fn bounds(&self) -> Aabb {
        self.instances.iter().fold(Aabb::EMPTY, |b, i| {
            b.union(self.meshes[i.mesh].mesh.bounds().transformed(&i.transform))
        })
    }

    /// Every instance baked into one mesh in file space (a species made from a file):
    /// mirrored instances get their winding flipped so fronts stay fronts.
    pub fn bake(&self) -> SpeciesModel {
        let mut mesh = TriangleMesh::default();
        for (index, instance) in self.instances.iter().enumerate() {
            let source = &self.meshes[instance.mesh].mesh;
            let m = instance.transform;
            let positions: Vec<Vec3> = source
                .positions
                .iter()
                .map(|&p| m.transform_point3(p))
                .collect();
            // A transform that overflows (huge scales in a node chain) would put ∞ into
            // the mesh: leave that instance out rather than the whole model.
            if !positions.iter().all(|p| p.is_finite()) {
                tracing::warn!(
                    "{}: instance {index} of mesh {} left out of the baked model: its transform \
                     gives non-finite positions",
                    self.path.display(),
                    instance.mesh
                );
                continue;
            }
            let normal_matrix = m.matrix3.inverse().transpose();
            let mirrored = m.matrix3.determinant() < 0.0;
            let base = mesh.positions.len() as u32;
            mesh.positions.extend(positions);
            mesh.normals.extend(
                source
                    .normals
                    .iter()
                    .map(|&n| Vec3::from(normal_matrix * Vec3A::from(n)).normalize_or(Vec3::Y)),
            );
            mesh.uvs.extend_from_slice(&source.uvs);
            mesh.indices.extend(source.indices.iter().map(|&[a, b, c]| {
                if mirrored {
                    [a + base, c + base, b + base]
                } else {
                    [a + base, b + base, c + base]
                }
            }));
            mesh.shaders.extend_from_slice(&source.shaders);
        }
        SpeciesModel {
            mesh,
            shaders: self.shaders.clone(),
        }
    }

    /// The chosen camera, or `None` when the file has none and the choice is `First`.
    pub fn camera(&self, choice: &CameraChoice) -> Result<Option<&GltfCamera>, GltfError> {
        let missing = |what: String| GltfError {
            path: self.path.clone(),
            location: None,
            message: format!(
                "no camera {what} (the file has {}: {})",
                self.cameras.len(),
                self.cameras
                    .iter()
                    .enumerate()
                    .map(|(i, c)| format!("{i} '{}'", c.name))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        };
        match choice {
            CameraChoice::First => Ok(self.cameras.first()),
            CameraChoice::Index(i) => self
                .cameras
                .get(*i)
                .map(Some)
                .ok_or_else(|| missing(format!("with index {i}"))),
            CameraChoice::Named(name) => self
                .cameras
                .iter()
                .find(|c| &c.name == name)
                .map(Some)
                .ok_or_else(|| missing(format!("named '{name}'"))),
        }
    }

    /// A scene of the file's instances under a default sun and sky, seen through the
    /// chosen camera (or one that frames the bounds from the front).
    pub fn into_scene(self, choice: &CameraChoice) -> Result<SceneBuild, SceneError> {
        let start = Instant::now();
        let (camera, camera_transform) = match self.camera(choice)? {
            Some(c) => {
                let (_, rotation, translation) = c.transform.to_scale_rotation_translation();
                (
                    Camera {
                        vertical_fov: c.yfov,
                        ..Camera::default()
                    },
                    Transform::from_translation(translation).with_rotation(rotation.normalize()),
                )
            }
            None => framing_view(self.bounds()),
        };
        let name = self
            .path
            .file_stem()
            .map_or("gltf".into(), |s| s.to_string_lossy().into_owned());
        // Every mesh's BLAS at once on the current pool (each build is parallel inside
        // too, which small meshes are not); the library keeps the file's mesh order.
        let blas_start = Instant::now();
        let built: Vec<Geometry> = self
            .meshes
            .into_par_iter()
            .map(|m| {
                Geometry::new(&m.name, m.mesh, BuildParams::BOTTOM_LEVEL).map_err(|e| {
                    SceneError::Mesh {
                        scene: name.clone(),
                        mesh: m.name.clone(),
                        source: e,
                    }
                })
            })
            .collect::<Result<_, _>>()?;
        let blas_time = blas_start.elapsed();
        let mut library = GeometryLibrary::default();
        let mut species = Vec::new();
        for geometry in built {
            let name = geometry.name.clone();
            let id = library.add(geometry);
            species.push(Species { name, geometry: id });
        }
        let mut sheared = 0usize;
        let plants = self
            .instances
            .iter()
            .map(|i| {
                let (scale, rotation, translation) = i.transform.to_scale_rotation_translation();
                // Plants carry translation-rotation-scale; a sheared node matrix cannot
                // be represented and is approximated (and counted).
                let rebuilt =
                    Affine3A::from_scale_rotation_translation(scale, rotation, translation);
                let size = i
                    .transform
                    .matrix3
                    .abs()
                    .to_cols_array()
                    .into_iter()
                    .fold(1.0f32, f32::max);
                if !rebuilt.abs_diff_eq(i.transform, 1e-4 * size) {
                    sheared += 1;
                }
                Plant {
                    geometry: species[i.mesh].geometry,
                    transform: Transform::from_translation(translation)
                        .with_rotation(rotation.normalize())
                        .with_scale(scale),
                    layer: 0,
                }
            })
            .collect();
        // Instances whose node or an ancestor of it is animated move with the animation.
        let node_animation = self.animation.map(|animation| {
            let animated: Vec<bool> = {
                let mut moved = vec![false; animation.parents.len()];
                for channel in &animation.channels {
                    if let Some(m) = moved.get_mut(channel.node) {
                        *m = true;
                    }
                }
                (0..moved.len())
                    .map(|mut node| {
                        for _ in 0..1024 {
                            if moved[node] {
                                return true;
                            }
                            match animation.parents[node] {
                                Some(parent) if parent < moved.len() => node = parent,
                                _ => return false,
                            }
                        }
                        false
                    })
                    .collect()
            };
            let bound = self
                .instances
                .iter()
                .enumerate()
                .filter(|(_, i)| animated.get(i.node_index).copied().unwrap_or(false))
                .map(|(plant, i)| (plant, i.node_index, i.local))
                .collect();
            (animation, bound)
        });
        if sheared > 0 {
            tracing::warn!(
                "{}: {sheared} instances have sheared transforms, approximated by scale, rotation and translation",
                self.path.display()
            );
        }
        Ok(SceneBuild {
            name,
            library,
            species,
            layers: vec!["glTF nodes".into()],
            layer_spacing: vec![0.0],
            wind: None,
            camera_path: None,
            sway_factors: Vec::new(),
            node_animation,
            terrain: None,
            height_field: None,
            shaders: self.shaders,
            plants,
            sun: Some(DirectionalLight {
                direction: Vec3::new(0.4, 0.8, 0.45).normalize(),
                irradiance: Vec3::splat(2.5),
            }),
            sky: Some(SkyLight {
                zenith: Vec3::new(0.5, 0.6, 0.8),
                horizon: Vec3::splat(0.8),
                ground: Vec3::splat(0.3),
            }),
            environment: None,
            camera,
            camera_transform,
            generate_time: start.elapsed() - blas_time,
            blas_time,
        })
    }
}

/// A camera in front of (+Z) and slightly above the bounds, far enough to see them whole.
pub(super) fn framing_view(bounds: Aabb) -> (Camera, Transform) {
    let camera = Camera {
        vertical_fov: 45f32.to_radians(),
        ..Camera::default()
    };
    if bounds.is_empty() {
        return (
            camera,
            Transform::looking_at(Vec3::Z * 5.0, Vec3::ZERO, Vec3::Y),
        );
    }
    let centre = Vec3::from(bounds.center());
    let radius = (Vec3::from(bounds.extent()).length() * 0.5).max(1e-3);
    let distance = radius / (camera.vertical_fov * 0.5).sin() * 1.05;
    let direction = Vec4::new(0.0, 0.25, 1.0, 0.0).truncate().normalize();
    (
        camera,
        Transform::looking_at(centre + direction * distance, centre, Vec3::Y),
    )
}

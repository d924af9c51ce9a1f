//! Writes a built-in scene (or a scene file) in the flat little-endian layout the Embree 3
//! comparison harness reads ("MFRAW002", described in `benches/README.md`), so that
//! Embree traces the very geometry, placements, alpha masks and camera Sylva traces. The
//! harness knows one leaf texture, so every alpha-masked shader gets a cell of one atlas
//! holding its mask (Sylva's own test, `Shader::is_opaque_at`, at 256 × 256 points of the
//! cell) and its triangles' UVs are moved into that cell. The harness has no separate
//! sun: the sun becomes a 3° disc in the sky map carrying as much luminous power as the
//! rest of the sky, so about half of its light samples go to the sun, as Sylva traces one
//! sun ray and one environment sample a hit at `--light-samples 1`.
//!
//! `cargo run --release --example export_embree_raw -- paper paper.raw`

use anyhow::{Context, Result, bail};
use glam::{Affine3A, Vec2, Vec3, Vec3A};
use std::collections::{BTreeMap, HashMap};
use std::f64::consts::PI;
use std::io::{BufWriter, Write};
use sylva::engine::environment::uv_to_direction;
use sylva::prelude::build_scene;
use sylva::scenes::SceneBuild;

/// Texels per atlas cell edge.
const CELL: u32 = 256;
/// Width and height of the written sky map.
const SKY: (u32, u32) = (512, 256);
/// Angular radius of the sun's disc in the sky map, degrees.
const SUN_RADIUS_DEG: f32 = 1.5;
/// Incoherent test rays the harness also traces (from the camera, random directions).
const TEST_RAYS: u32 = 4096;

/// Little-endian output.
struct Raw(BufWriter<std::fs::File>);

impl Raw {
    fn u32(&mut self, v: u32) -> Result<()> {
        Ok(self.0.write_all(&v.to_le_bytes())?)
    }

    fn f32s(&mut self, values: impl IntoIterator<Item = f32>) -> Result<()> {
        for v in values {
            self.0.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    }
}

/// One alpha mask per masked shader, packed in a grid of cells.
struct Atlas {
    columns: u32,
    rows: u32,
    cell_of: Vec<Option<u32>>,
    alpha: Vec<u8>,
}

impl Atlas {
    fn new(scene: &SceneBuild) -> Self {
        let masked: Vec<usize> = (0..scene.shaders.len())
            .filter(|&s| scene.shaders[s].is_alpha_masked())
            .collect();
        let columns = ((masked.len() as f32).sqrt().ceil() as u32).max(1);
        let rows = (masked.len() as u32).div_ceil(columns).max(1);
        let width = columns * CELL;
        let mut alpha = vec![0u8; (width * rows * CELL) as usize];
        let mut cell_of = vec![None; scene.shaders.len()];
        for (cell, &s) in masked.iter().enumerate() {
            cell_of[s] = Some(cell as u32);
            let (cx, cy) = (cell as u32 % columns, cell as u32 / columns);
            for y in 0..CELL {
                for x in 0..CELL {
                    let uv = Vec2::new(x as f32 + 0.5, y as f32 + 0.5) / CELL as f32;
                    let index = (cy * CELL + y) * width + cx * CELL + x;
                    alpha[index as usize] = if scene.shaders[s].is_opaque_at(uv) {
                        255
                    } else {
                        0
                    };
                }
            }
        }
        Self {
            columns,
            rows,
            cell_of,
            alpha,
        }
    }

    /// `uv` of a triangle of shader `shader`, moved into its cell when it has one.
    fn uv(&self, shader: u32, uv: Vec2) -> Vec2 {
        match self.cell_of.get(shader as usize).copied().flatten() {
            Some(cell) => {
                let corner = Vec2::new((cell % self.columns) as f32, (cell / self.columns) as f32);
                let inside = uv.clamp(Vec2::ZERO, Vec2::splat(1.0 - 1e-6));
                (corner + inside) / Vec2::new(self.columns as f32, self.rows as f32)
            }
            None => uv,
        }
    }
}

fn row_major(a: &Affine3A) -> [f32; 12] {
    let (x, y, z, t) = (
        a.matrix3.x_axis,
        a.matrix3.y_axis,
        a.matrix3.z_axis,
        a.translation,
    );
    std::array::from_fn(|i| [x, y, z, t][i % 4][i / 4])
}

/// Meshes split into one primitive per shader (the harness's materials: 0 leaf with the
/// alpha test, 1 bark, 2 ground). The terrain is flagged: the harness adds it to the top
/// level as it is, which is where Sylva places it (at the origin, unmoved).
fn write_meshes(raw: &mut Raw, scene: &SceneBuild, atlas: &Atlas) -> Result<usize> {
    let terrain = scene.terrain.map(|t| t.0 as usize);
    raw.u32(scene.library.geometries.len() as u32)?;
    let mut triangles = 0;
    for (g, geometry) in scene.library.geometries.iter().enumerate() {
        let mesh = &geometry.mesh;
        let is_terrain = Some(g) == terrain;
        let mut by_shader: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
        for (t, &s) in mesh.shaders.iter().enumerate() {
            by_shader.entry(s).or_default().push(t);
        }
        raw.u32(u32::from(is_terrain))?;
        raw.u32(by_shader.len() as u32)?;
        for (&shader, tris) in &by_shader {
            let mut local = HashMap::new();
            let mut vertices = Vec::new();
            let mut indices = Vec::with_capacity(tris.len() * 3);
            for &t in tris {
                for &v in &mesh.indices[t] {
                    let next = vertices.len() as u32;
                    let i = *local.entry(v).or_insert_with(|| {
                        vertices.push(v as usize);
                        next
                    });
                    indices.push(i);
                }
            }
            triangles += tris.len();
            let material = match (
                atlas.cell_of.get(shader as usize).copied().flatten(),
                is_terrain,
            ) {
                (Some(_), _) => 0,
                (None, false) => 1,
                (None, true) => 2,
            };
            raw.u32(material)?;
            raw.u32(vertices.len() as u32)?;
            raw.u32(tris.len() as u32)?;
            raw.f32s(vertices.iter().flat_map(|&v| mesh.positions[v].to_array()))?;
            raw.f32s(vertices.iter().flat_map(|&v| {
                let uv = mesh.uvs.get(v).copied().unwrap_or(Vec2::ZERO);
                atlas.uv(shader, uv).to_array()
            }))?;
            for i in indices {
                raw.u32(i)?;
            }
        }
    }
    Ok(triangles)
}

/// The sky as the harness maps it (row 0 the zenith, texel centres), the sun's disc added.
fn sky_map(scene: &SceneBuild, sun: Vec3) -> Vec<Vec3> {
    let (width, height) = SKY;
    let radiance = |d: Vec3| -> Vec3 {
        if let Some(environment) = &scene.environment {
            environment.map.radiance(d.into()).into()
        } else if let Some(sky) = &scene.sky {
            sky.radiance(d.into()).into()
        } else {
            Vec3::ZERO
        }
    };
    let mut texels = Vec::with_capacity((width * height) as usize);
    let (mut sky_power, mut sun_area, mut sun_texels) = (0.0, 0.0, Vec::new());
    for y in 0..height {
        let theta = PI * (f64::from(y) + 0.5) / f64::from(height);
        let area = (2.0 * PI / f64::from(width)) * (PI / f64::from(height)) * theta.sin();
        for x in 0..width {
            // The harness's texel direction, (sin φ sin θ, cos θ, −cos φ sin θ) at
            // φ = 2π (x + ½) / width, is Sylva's lat-long mapping at the texel's centre.
            let d = uv_to_direction(
                (x as f32 + 0.5) / width as f32,
                (y as f32 + 0.5) / height as f32,
            );
            let l = radiance(d);
            sky_power += f64::from(0.2126 * l.x + 0.7152 * l.y + 0.0722 * l.z) * area;
            if d.dot(sun) > SUN_RADIUS_DEG.to_radians().cos() {
                sun_texels.push(texels.len());
                sun_area += area;
            }
            texels.push(l);
        }
    }
    // A scene without sky light still needs a map with some light in it: the harness
    // divides by its total. Then the sun carries all of it.
    let sun_power = if sky_power > 0.0 { sky_power } else { 1.0 };
    let sun_radiance = if sun_area > 0.0 {
        (sun_power / sun_area) as f32
    } else {
        0.0
    };
    for i in sun_texels {
        texels[i] += Vec3::splat(sun_radiance);
    }
    texels
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [scene_name, out] = args.as_slice() else {
        bail!(
            "usage: export_embree_raw SCENE OUT.raw (SCENE: meadow, forest, paper or a .toml file)"
        );
    };
    let scene = build_scene(scene_name, 0).with_context(|| format!("building {scene_name}"))?;
    if let Some((i, s)) = scene
        .shaders
        .iter()
        .enumerate()
        .find(|(i, s)| s.id.0 as usize != *i)
    {
        bail!(
            "shader {i} has id {}: the export needs ids equal to indices",
            s.id.0
        );
    }
    // Without a sun the disc stands at the zenith.
    let sun = scene.sun.map_or(Vec3::Y, |s| s.direction.normalize());
    let atlas = Atlas::new(&scene);
    let file = std::fs::File::create(out).with_context(|| format!("creating {out}"))?;
    let mut raw = Raw(BufWriter::new(file));
    raw.0.write_all(b"MFRAW002")?;
    let triangles = write_meshes(&mut raw, &scene, &atlas)?;
    // The plants, then the terrain's own entry as the anchor generator writes it (the
    // harness skips it when it places instances, and counts it out of its total).
    let terrain = scene.terrain.map(|t| (t.0, Affine3A::IDENTITY));
    let placements: Vec<(u32, Affine3A)> = scene
        .plants
        .iter()
        .map(|p| (p.geometry.0, p.transform.to_affine()))
        .chain(terrain)
        .collect();
    raw.u32(placements.len() as u32)?;
    for (geometry, transform) in &placements {
        raw.u32(*geometry)?;
        raw.f32s(row_major(transform))?;
    }
    raw.u32(atlas.columns * CELL)?;
    raw.u32(atlas.rows * CELL)?;
    raw.0.write_all(&atlas.alpha)?;
    let camera = scene.camera_transform.to_affine();
    let origin = Vec3::from(camera.translation);
    let forward = Vec3::from(camera.transform_vector3a(-Vec3A::Z)).normalize();
    let up = Vec3::from(camera.transform_vector3a(Vec3A::Y));
    let (width, height) = (scene.camera.width, scene.camera.height);
    let aspect = width as f32 / height as f32;
    let horizontal_fov = 2.0 * ((scene.camera.vertical_fov * 0.5).tan() * aspect).atan();
    raw.f32s(origin.to_array())?;
    raw.f32s((origin + forward).to_array())?;
    raw.f32s(up.to_array())?;
    raw.f32s([horizontal_fov.to_degrees()])?;
    raw.u32(width)?;
    raw.u32(height)?;
    raw.f32s(sun.to_array())?;
    let mut state = 0x1234_5678_u64;
    let mut random = || {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    let directions: Vec<Vec3> = (0..TEST_RAYS)
        .map(|_| Vec3::new(random() - 0.5, random() - 0.7, random() - 0.5).normalize_or(-Vec3::Y))
        .collect();
    raw.u32(TEST_RAYS)?;
    raw.f32s((0..TEST_RAYS).flat_map(|_| origin.to_array()))?;
    raw.f32s(directions.iter().flat_map(|d| d.to_array()))?;
    raw.u32(SKY.0)?;
    raw.u32(SKY.1)?;
    raw.f32s(sky_map(&scene, sun).iter().flat_map(|t| t.to_array()))?;
    // Bark and ground albedo, and a one-texel leaf colour: the harness's shading only.
    raw.f32s([0.3, 0.2, 0.1, 0.3, 0.3, 0.2])?;
    raw.u32(1)?;
    raw.u32(1)?;
    raw.0.write_all(&[60, 120, 40])?;
    raw.0.flush().with_context(|| format!("writing {out}"))?;
    println!(
        "{out}: {} meshes, {triangles} unique triangles, {} plants, {} masked shaders in a {}x{} atlas, camera {width}x{height} at {:.2}° across",
        scene.library.geometries.len(),
        scene.plants.len(),
        atlas.cell_of.iter().flatten().count(),
        atlas.columns * CELL,
        atlas.rows * CELL,
        horizontal_fov.to_degrees()
    );
    Ok(())
}

//! glTF import against the Khronos conformance models in `tests/data/`: each test
//! checks the property its model exists to test, plus bad files that must give errors
//! naming the file and the glTF path.
#![cfg(feature = "gltf")]

use glam::{Vec2, Vec3, Vec3A};
use std::path::{Path, PathBuf};
use sylva_engine::bvh::{BuildParams, TraversalStats};
use sylva_engine::camera::CameraView;
use sylva_engine::light::LightSet;
use sylva_engine::math::Ray;
use sylva_engine::opacity::OpacityMaps;
use sylva_engine::render::RenderScene;
use sylva_engine::shading::ShaderTable;
use sylva_engine::tlas::TopLevel;
use sylva_scenes::SceneBuild;
use sylva_scenes::gltf::{CameraChoice, GltfScene, import};

fn asset(relative: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data")
        .join(relative)
}

fn model(name: &str) -> PathBuf {
    asset(&format!("gltf/{name}/glTF-Binary/{name}.glb"))
}

/// A scene ready for ray queries.
struct Queryable {
    scene: SceneBuild,
    top_level: TopLevel,
    shaders: ShaderTable,
    lights: LightSet,
    opacity: OpacityMaps,
}

impl Queryable {
    fn new(imported: GltfScene) -> Self {
        let scene = imported.into_scene(&CameraChoice::First).unwrap();
        let top_level = TopLevel::build(
            &scene.library,
            &scene.instance_descs(),
            BuildParams::BALANCED,
        );
        let shaders = ShaderTable::new(scene.shaders.clone());
        let opacity = OpacityMaps::build(&scene.library, &shaders);
        Self {
            scene,
            top_level,
            shaders,
            lights: LightSet::default(),
            opacity,
        }
    }

    fn kernel(&self) -> RenderScene<'_> {
        RenderScene {
            geometry: &self.scene.library,
            top_level: &self.top_level,
            shaders: &self.shaders,
            lights: &self.lights,
            opacity: &self.opacity,
        }
    }
}

#[test]
fn simple_instancing_yields_125_distinct_instances_in_both_encodings() {
    for path in [
        asset("gltf/SimpleInstancing/glTF/SimpleInstancing.gltf"),
        model("SimpleInstancing"),
    ] {
        let scene = import(&path).unwrap();
        assert_eq!(scene.instances.len(), 125, "{}", path.display());
        let mut origins: Vec<[u32; 3]> = scene
            .instances
            .iter()
            .map(|i| i.transform.translation.to_array().map(f32::to_bits))
            .collect();
        origins.sort_unstable();
        origins.dedup();
        assert_eq!(origins.len(), 125, "every instance stands elsewhere");
        // No material: everything uses the default (last) slot.
        let default = scene.shaders.len() as u32 - 1;
        assert!(scene.meshes[0].mesh.shaders.iter().all(|&s| s == default));
    }
}

/// Alpha (0–1) of an RGBA or grey+alpha image decoded by the gltf crate itself, at
/// integer texel `(x, y)`.
fn raw_alpha(image: &gltf::image::Data, x: u32, y: u32) -> f32 {
    let channels = match image.format {
        gltf::image::Format::R8G8B8A8 => 4,
        gltf::image::Format::R8G8 => 2,
        _ => return 1.0,
    };
    let i = ((y * image.width + x) as usize + 1) * channels - 1;
    image.pixels[i] as f32 / 255.0
}

#[test]
fn alpha_modes_cut_holes_exactly_where_alpha_is_below_the_cutoff() {
    let path = model("AlphaBlendModeTest");
    let imported = import(&path).unwrap();
    let by_name = |name: &str| {
        let (document, _, _) = gltf::import(&path).unwrap();
        document
            .materials()
            .find(|m| m.name() == Some(name))
            .and_then(|m| m.index())
            .unwrap()
    };
    let cutoffs = [
        ("MatOpaque", None),
        ("MatBlend", Some(0.5)),
        ("MatCutoff25", Some(0.25)),
        ("MatCutoffDefault", Some(0.5)),
        ("MatCutoff75", Some(0.75)),
    ];
    for (name, cutoff) in cutoffs {
        assert_eq!(
            imported.shaders[by_name(name)].alpha_cutoff,
            cutoff,
            "{name}"
        );
    }
    // The oracle: the gltf crate's own decoding of the images, read texel by texel.
    let (document, _, images) = gltf::import(&path).unwrap();
    let q = Queryable::new(imported);
    let kernel = q.kernel();
    let mut checked = [0usize; 2];
    for (name, cutoff) in cutoffs {
        let material = document.materials().nth(by_name(name)).unwrap();
        let image = &images[material
            .pbr_metallic_roughness()
            .base_color_texture()
            .unwrap()
            .texture()
            .source()
            .index()];
        let slot = by_name(name) as u32;
        for (i, plant) in q.scene.plants.iter().enumerate() {
            let mesh = &q.scene.library.get(plant.geometry).unwrap().mesh;
            let transform = plant.transform.to_affine();
            for t in 0..mesh.triangle_count() {
                if mesh.shaders[t] != slot {
                    continue;
                }
                let [a, b, c] = mesh.indices[t].map(|k| k as usize);
                for k in 0..40 {
                    // Deterministic points spread over the triangle.
                    let (u, v) = (
                        (k as f32 * 0.618_034).fract(),
                        (k as f32 * 0.414_214).fract(),
                    );
                    let (u, v) = if u + v > 1.0 {
                        (1.0 - u, 1.0 - v)
                    } else {
                        (u, v)
                    };
                    // Keep off the edges: a ray through a mesh's outer corner may miss.
                    let (u, v) = (0.02 + 0.96 * u, 0.02 + 0.96 * v);
                    let (u, v) = (u / (1.0 + 0.04), v / (1.0 + 0.04));
                    let w = 1.0 - u - v;
                    let uv = mesh.uvs[a] * w + mesh.uvs[b] * u + mesh.uvs[c] * v;
                    let p = mesh.positions[a] * w + mesh.positions[b] * u + mesh.positions[c] * v;
                    let n = (mesh.positions[b] - mesh.positions[a])
                        .cross(mesh.positions[c] - mesh.positions[a]);
                    let world = transform.transform_point3(p);
                    let normal = transform.matrix3.inverse().transpose() * Vec3A::from(n);
                    let normal = Vec3::from(normal).normalize();
                    // Bilinear filtering mixes four texels: judge only where all four
                    // agree on which side of the cutoff they lie.
                    let (tx, ty) = (
                        uv.x * image.width as f32 - 0.5,
                        uv.y * image.height as f32 - 0.5,
                    );
                    let (x0, y0) = (tx.floor() as i64, ty.floor() as i64);
                    let texel = |x: i64, y: i64| {
                        raw_alpha(
                            image,
                            x.rem_euclid(image.width as i64) as u32,
                            y.rem_euclid(image.height as i64) as u32,
                        )
                    };
                    let corners = [
                        texel(x0, y0),
                        texel(x0 + 1, y0),
                        texel(x0, y0 + 1),
                        texel(x0 + 1, y0 + 1),
                    ];
                    let expected = match cutoff {
                        None => true,
                        Some(c) if corners.iter().all(|&a| a >= c + 0.01) => true,
                        Some(c) if corners.iter().all(|&a| a < c - 0.01) => false,
                        _ => continue,
                    };
                    let origin = Vec3A::from(world + normal * 1e-3);
                    let ray = Ray::segment(origin, -Vec3A::from(normal), 2e-3);
                    let hit = kernel.closest(&ray, &mut TraversalStats::default());
                    let hit_this = hit.is_some_and(|h| h.instance as usize == i);
                    assert_eq!(hit_this, expected, "{name}: uv {uv}, alpha {corners:?}");
                    checked[usize::from(expected)] += 1;
                }
            }
        }
    }
    assert!(
        checked[0] > 50 && checked[1] > 200,
        "holes/solid checked: {checked:?}"
    );
}

/// The principal axis of a point cloud (power iteration on its covariance).
fn principal_axis(points: &[Vec3]) -> Vec3 {
    let mean = points.iter().copied().sum::<Vec3>() / points.len() as f32;
    let mut cov = glam::Mat3::ZERO;
    for p in points {
        let d = *p - mean;
        cov += glam::Mat3::from_cols(d * d.x, d * d.y, d * d.z);
    }
    let mut axis = Vec3::new(0.3, 0.5, 0.8);
    for _ in 0..100 {
        axis = (cov * axis).normalize();
    }
    axis
}

#[test]
fn orientation_test_arrows_point_at_their_targets() {
    let scene = import(&model("OrientationTest")).unwrap();
    let world_points = |node: &str| -> Vec<Vec3> {
        let instance = scene.instances.iter().find(|i| i.node == node).unwrap();
        scene.meshes[instance.mesh]
            .mesh
            .positions
            .iter()
            .map(|&p| instance.transform.transform_point3(p))
            .collect()
    };
    for arrow in ["X1", "X2", "Y1", "Y2", "Z1", "Z2"] {
        let shaft = world_points(&format!("Arrow{arrow}"));
        let target = world_points(&format!("Target{arrow}"));
        let centre = shaft.iter().copied().sum::<Vec3>() / shaft.len() as f32;
        let aim = (target.iter().copied().sum::<Vec3>() / target.len() as f32 - centre).normalize();
        let axis = principal_axis(&shaft);
        assert!(
            axis.dot(aim).abs() > 0.97,
            "Arrow{arrow} runs along {axis}, its target lies along {aim}"
        );
    }
}

/// Counts camera-ray hits by the hue of their albedo: (green ticks, red crosses).
fn ticks_and_crosses(q: &Queryable, width: u32, height: u32) -> (usize, usize) {
    let mut camera = q.scene.camera;
    camera.width = width;
    camera.height = height;
    let view = CameraView::new(&camera, &q.scene.camera_transform.to_affine());
    let kernel = q.kernel();
    let (mut green, mut red) = (0, 0);
    for y in 0..height {
        for x in 0..width {
            let ray = view.ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5), Vec2::ZERO);
            let Some(hit) = kernel.closest(&ray, &mut TraversalStats::default()) else {
                continue;
            };
            let surface = kernel.surface(&hit, ray.direction);
            let c = q.shaders.get(surface.shader).albedo(surface.uv);
            if c.y > 0.25 && c.x < 0.5 * c.y && c.z < 0.5 * c.y {
                green += 1;
            }
            if c.x > 0.25 && c.y < 0.5 * c.x && c.z < 0.5 * c.x {
                red += 1;
            }
        }
    }
    (green, red)
}

#[test]
fn negative_scale_test_shows_ticks_and_no_crosses() {
    // The model draws green ticks on the faces that must be seen and red crosses on the
    // faces that must be culled; a renderer that ignores the determinant's winding flip
    // shows crosses in the mirrored row.
    let q = Queryable::new(import(&model("NegativeScaleTest")).unwrap());
    let (green, red) = ticks_and_crosses(&q, 400, 300);
    assert!(green > 200, "{green} tick pixels");
    assert!(
        red * 50 < green,
        "{red} cross pixels against {green} tick pixels"
    );
}

#[test]
fn two_sided_plane_is_seen_from_both_sides() {
    let path = asset("gltf/TwoSidedPlane/glTF/TwoSidedPlane.gltf");
    let q = Queryable::new(import(&path).unwrap());
    assert!(
        q.scene
            .shaders
            .iter()
            .take(q.scene.shaders.len() - 1)
            .all(|s| s.double_sided)
    );
    let kernel = q.kernel();
    let bounds = q.top_level.bvh.bounds();
    let centre = bounds.center();
    let mut seen = 0;
    for axis in [Vec3A::X, Vec3A::Y, Vec3A::Z] {
        for sign in [1.0, -1.0] {
            let dir = axis * sign;
            let ray = Ray::new(centre - dir * 10.0, dir);
            seen += usize::from(
                kernel
                    .closest(&ray, &mut TraversalStats::default())
                    .is_some(),
            );
        }
    }
    assert_eq!(
        seen, 2,
        "the plane is hit from its front and its back, and edge-on never"
    );
}

#[test]
fn texture_coordinate_origin_is_the_top_left_of_the_image() {
    // BoxTextured and TextureCoordinateTest load with their textures; sampling UV
    // (0.01, 0.01) reads the image's first row, as the gltf crate decodes it.
    for name in ["TextureCoordinateTest", "BoxTextured"] {
        let path = model(name);
        let scene = import(&path).unwrap();
        let (_, _, images) = gltf::import(&path).unwrap();
        let textured: Vec<_> = scene
            .shaders
            .iter()
            .filter_map(|s| s.texture.clone())
            .collect();
        assert!(!textured.is_empty(), "{name} has a texture");
        let texture = &textured[0];
        let image = images
            .iter()
            .find(|i| i.width == texture.width() && i.height == texture.height())
            .unwrap();
        let channels = image.pixels.len() / (image.width * image.height) as usize;
        let first = &image.pixels[..3.min(channels)];
        let sampled = texture.sample(
            Vec2::new(0.5, 0.5) / Vec2::new(texture.width() as f32, texture.height() as f32),
        );
        let expected = sylva_engine::shading::srgb_to_linear(first[0] as f32 / 255.0);
        assert!(
            (sampled.x - expected).abs() < 1e-3,
            "{name}: {sampled} vs {first:?}"
        );
    }
}

#[test]
fn plant_models_from_the_asset_packs_load_and_stand_upright() {
    let mut loaded = 0;
    for pack in [
        "plants/quaternius_ultimate_nature",
        "plants/kenney_platformer_kit",
    ] {
        for entry in std::fs::read_dir(asset(pack)).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_none_or(|e| e != "glb") {
                continue;
            }
            let scene = import(&path).unwrap();
            let model = scene.bake();
            model.mesh.check().unwrap();
            assert!(model.mesh.triangle_count() > 0, "{}", path.display());
            let b = model.mesh.bounds();
            // Z-up centimetres converted by the node transforms: taller than wide-ish
            // and about metre-sized, not 100× off.
            let size = b.extent();
            assert!(
                size.max_element() < 50.0 && size.max_element() > 0.05,
                "{}: {b:?}",
                path.display()
            );
            loaded += 1;
        }
    }
    assert!(loaded >= 3, "{loaded} plant models");
}

/// Writes `files` into a fresh temporary folder and returns it.
fn scratch(name: &str, files: &[(&str, &[u8])]) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sylva-gltf-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (file, bytes) in files {
        std::fs::write(dir.join(file), bytes).unwrap();
    }
    dir
}

/// A one-triangle glTF with its buffer inline as base64; `positions` are 9 floats.
fn triangle_gltf(positions: [f32; 9], indices: Option<[u16; 3]>, extra: &str) -> String {
    let mut bytes: Vec<u8> = positions.iter().flat_map(|f| f.to_le_bytes()).collect();
    let index_part = indices.map(|i| {
        let start = bytes.len();
        bytes.extend(i.iter().flat_map(|v| v.to_le_bytes()));
        bytes.extend([0, 0]);
        start
    });
    let b64 = base64(&bytes);
    let (index_view, index_accessor, index_ref) = match index_part {
        Some(offset) => (
            format!(r#",{{"buffer":0,"byteOffset":{offset},"byteLength":6}}"#),
            r#",{"bufferView":1,"componentType":5123,"count":3,"type":"SCALAR"}"#.to_string(),
            r#","indices":1"#.to_string(),
        ),
        None => (String::new(), String::new(), String::new()),
    };
    format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}{index_ref}}}]}}],
"buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{b64}"}}],
"bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":36}}{index_view}],
"accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}}{index_accessor}]{extra}}}"#,
        bytes.len()
    )
}

fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for chunk in bytes.chunks(3) {
        let n = chunk
            .iter()
            .enumerate()
            .fold(0u32, |n, (i, &b)| n | (b as u32) << (16 - 8 * i));
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

#[test]
fn a_valid_inline_triangle_imports_with_flat_normals() {
    let text = triangle_gltf(
        [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        Some([0, 1, 2]),
        "",
    );
    let dir = scratch("ok", &[("t.gltf", text.as_bytes())]);
    let scene = import(&dir.join("t.gltf")).unwrap();
    let mesh = &scene.meshes[0].mesh;
    assert_eq!(mesh.triangle_count(), 1);
    assert!(
        mesh.normals.iter().all(|n| *n == Vec3::Z),
        "{:?}",
        mesh.normals
    );
}

#[test]
fn bad_files_are_errors_naming_the_file_and_the_gltf_path() {
    let glb = std::fs::read(model("BoxTextured")).unwrap();
    let two_sided = std::fs::read(asset("gltf/TwoSidedPlane/glTF/TwoSidedPlane.gltf")).unwrap();
    let out_of_range = triangle_gltf(
        [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        Some([0, 1, 7]),
        "",
    );
    let bad_image = triangle_gltf(
        [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        None,
        r#","images":[{"uri":"leaf.png"}],"textures":[{"source":0}],"materials":[{"name":"leaf","pbrMetallicRoughness":{"baseColorTexture":{"index":0}}}]"#,
    )
    .replace(r#""attributes":{"POSITION":0}"#, r#""attributes":{"POSITION":0},"material":0"#);
    // Indices declared as float vectors: gltf's reader would misread them (fuzz finding).
    let float_indices = triangle_gltf(
        [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        Some([0, 1, 2]),
        "",
    )
    .replace(
        r#""componentType":5123,"count":3,"type":"SCALAR""#,
        r#""componentType":5126,"count":1,"type":"VEC2""#,
    );
    assert!(float_indices.contains(r#""count":1,"type":"VEC2""#));
    // Positions 12 bytes apart cannot sit 11 bytes apart (fuzz finding).
    let short_stride = triangle_gltf(
        [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        Some([0, 1, 2]),
        "",
    )
    .replacen(
        r#""byteOffset":0,"byteLength":36}"#,
        r#""byteOffset":0,"byteLength":36,"byteStride":11}"#,
        1,
    );
    assert!(short_stride.contains(r#""byteStride":11"#));
    let dir = scratch(
        "bad",
        &[
            ("float_indices.gltf", float_indices.as_bytes()),
            ("short_stride.gltf", short_stride.as_bytes()),
            ("truncated.glb", &glb[..glb.len() / 2]),
            ("missing_buffer.gltf", &two_sided),
            ("out_of_range.gltf", out_of_range.as_bytes()),
            ("bad_image.gltf", bad_image.as_bytes()),
            ("leaf.png", b"\x89PNG\r\n\x1a\nnot really a png"),
            ("garbage.glb", b"glTF\x02\x00\x00\x00garbage"),
        ],
    );
    let cases = [
        ("truncated.glb", ""),
        ("missing_buffer.gltf", "buffers[0].uri"),
        ("out_of_range.gltf", "meshes[0].primitives[0].indices"),
        ("float_indices.gltf", "meshes[0].primitives[0].indices"),
        (
            "short_stride.gltf",
            "meshes[0].primitives[0].attributes.POSITION",
        ),
        ("bad_image.gltf", "baseColorTexture of material 'leaf'"),
        ("garbage.glb", ""),
        ("does_not_exist.glb", "cannot read"),
    ];
    for (file, place) in cases {
        let e = import(&dir.join(file)).unwrap_err().to_string();
        assert!(e.contains(file) && e.contains(place), "{file}: {e}");
    }
}

#[test]
fn nan_vertices_are_dropped_and_counted() {
    let text = triangle_gltf(
        [0.0, 0.0, 0.0, f32::NAN, 0.0, 0.0, 0.0, 1.0, 0.0],
        Some([0, 1, 2]),
        "",
    );
    let dir = scratch("nan", &[("nan.gltf", text.as_bytes())]);
    let scene = import(&dir.join("nan.gltf")).unwrap();
    assert_eq!(scene.report.non_finite_vertices, 1);
    assert_eq!(scene.report.dropped_triangles, 1);
    assert_eq!(scene.meshes[0].mesh.triangle_count(), 0);
}

#[test]
fn cameras_are_chosen_by_name_or_index_and_missing_ones_are_errors() {
    let path = model("BoxTextured");
    let scene = import(&path).unwrap();
    // BoxTextured has no camera: the first choice frames the model, others are errors.
    assert!(scene.camera(&CameraChoice::First).unwrap().is_none());
    let e = scene
        .camera(&CameraChoice::parse("3"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("BoxTextured.glb") && e.contains("index 3"),
        "{e}"
    );
    let e = scene
        .camera(&CameraChoice::parse("main"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("named 'main'"), "{e}");
    let built = scene.into_scene(&CameraChoice::First).unwrap();
    let view = CameraView::new(&built.camera, &built.camera_transform.to_affine());
    let centre = view.ray(Vec2::new(320.0, 240.0), Vec2::ZERO);
    assert!(
        centre.direction.z < -0.5,
        "the framing view looks at the model from +Z"
    );
}

/// Inputs the `gltf_import` fuzz target once failed on (`fuzz/regressions/`): each is an
/// error or a model whose baked positions are all finite.
#[test]
fn fuzz_regressions_import_cleanly_or_fail_with_an_error() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/regressions/gltf_import");
    let mut checked = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let data = std::fs::read(&path).unwrap();
        if let Ok(scene) = sylva_scenes::gltf::import_slice(&data, Path::new("/nonexistent/f.glb"))
        {
            let model = scene.bake();
            assert!(
                model.mesh.positions.iter().all(|p| p.is_finite()),
                "{}",
                path.display()
            );
        }
        checked += 1;
    }
    assert!(checked >= 1);
}

/// Five unit quads facing +z in a row (quad `i` at x = 2i, material `i`), with UVs whose
/// origin is the image's top left; `materials` is the JSON array of the five materials,
/// `extra` adds top-level members (textures, images, samplers).
fn quads_gltf(materials: &str, extra: &str) -> String {
    let positions: [f32; 12] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0];
    let uvs: [f32; 8] = [0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0];
    let indices: [u16; 6] = [0, 1, 2, 0, 2, 3];
    let mut bytes: Vec<u8> = positions.iter().flat_map(|f| f.to_le_bytes()).collect();
    bytes.extend(uvs.iter().flat_map(|f| f.to_le_bytes()));
    bytes.extend(indices.iter().flat_map(|i| i.to_le_bytes()));
    let nodes: Vec<String> = (0..5)
        .map(|i| format!(r#"{{"mesh":{i},"translation":[{},0,0]}}"#, 2 * i))
        .collect();
    let meshes: Vec<String> = (0..5)
        .map(|i| {
            format!(
                r#"{{"primitives":[{{"attributes":{{"POSITION":0,"TEXCOORD_0":1}},"indices":2,"material":{i}}}]}}"#
            )
        })
        .collect();
    format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0,1,2,3,4]}}],
"nodes":[{}],"meshes":[{}],"materials":{materials},
"extensionsUsed":["KHR_materials_emissive_strength"],
"buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{}"}}],
"bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":48}},{{"buffer":0,"byteOffset":48,"byteLength":32}},{{"buffer":0,"byteOffset":80,"byteLength":12}}],
"accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
{{"bufferView":1,"componentType":5126,"count":4,"type":"VEC2"}},
{{"bufferView":2,"componentType":5123,"count":6,"type":"SCALAR"}}]{extra}}}"#,
        nodes.join(","),
        meshes.join(","),
        bytes.len(),
        base64(&bytes)
    )
}

/// What a camera ray straight at the point (x, y) of the quads' plane sees, with no
/// light in the scene but what surfaces emit.
fn shade_at(q: &Queryable, x: f32, y: f32) -> sylva_engine::render::ShadedSample {
    let ray = Ray::new(Vec3A::new(x, y, 5.0), Vec3A::NEG_Z);
    q.kernel().shade(
        &ray,
        &sylva_engine::sampling::SampleKey::new(0, 0, 0, 0, 0),
        &sylva_engine::render::SampleShading::plain(1),
        &mut TraversalStats::default(),
    )
}

#[test]
fn emissive_strength_test_quads_grow_brighter_to_the_right() {
    // The Khronos EmissiveStrengthTest's property (its files are not in this
    // repository): emissive colour [0.1, 0.5, 0.9] on all, KHR_materials_emissive_strength
    // absent on the first and 2, 4, 8, 16 on the others; black base colour.
    let strengths = [None, Some(2.0), Some(4.0), Some(8.0), Some(16.0)];
    let materials: Vec<String> = strengths
        .iter()
        .map(|s| {
            let extension = s.map_or(String::new(), |s: f32| {
                format!(r#","extensions":{{"KHR_materials_emissive_strength":{{"emissiveStrength":{s}}}}}"#)
            });
            format!(
                r#"{{"pbrMetallicRoughness":{{"baseColorFactor":[0,0,0,1]}},"emissiveFactor":[0.1,0.5,0.9]{extension}}}"#
            )
        })
        .collect();
    let text = quads_gltf(&format!("[{}]", materials.join(",")), "");
    let dir = scratch("emissive-strength", &[("e.gltf", text.as_bytes())]);
    let q = Queryable::new(import(&dir.join("e.gltf")).unwrap());
    for (i, strength) in strengths.iter().enumerate() {
        let shaded = shade_at(&q, 2.0 * i as f32 + 0.5, 0.5);
        let expected = Vec3A::new(0.1, 0.5, 0.9) * strength.unwrap_or(1.0);
        assert!(
            (shaded.radiance - expected).abs().max_element() < 1e-6 * expected.max_element(),
            "quad {i}: {} against {expected}",
            shaded.radiance
        );
        assert_eq!(
            shaded.emission, shaded.radiance,
            "quad {i}: all of it emitted"
        );
    }
    // Between the quads the ray meets nothing: no emission, no light.
    assert_eq!(shade_at(&q, 1.5, 0.5).radiance, Vec3A::ZERO);
}

#[test]
fn emissive_textures_are_srgb_and_follow_the_uv_origin_and_bad_factors_are_errors() {
    // A 4×1 emissive texture, red on the left half and sRGB mid-grey on the right, on
    // quad 0 (sampled at texel centres); quad 1 emits nothing (no emissive factor)
    // although it names the texture.
    let (red, grey) = ([255, 0, 0, 255], [128, 128, 128, 255]);
    let mut png = Vec::new();
    image::RgbaImage::from_raw(4, 1, [red, red, grey, grey].concat())
        .unwrap()
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    let textured = r#"{"emissiveFactor":[1,1,1],"emissiveTexture":{"index":0}}"#;
    let unlit = r#"{"emissiveTexture":{"index":0}}"#;
    let plain = r#"{}"#;
    let materials = format!("[{textured},{unlit},{plain},{plain},{plain}]");
    let extra = format!(
        r#","textures":[{{"source":0,"sampler":0}}],"samplers":[{{"wrapS":33071,"wrapT":33071}}],"images":[{{"uri":"data:image/png;base64,{}"}}]"#,
        base64(&png)
    );
    let text = quads_gltf(&materials, &extra);
    let dir = scratch("emissive-texture", &[("t.gltf", text.as_bytes())]);
    let q = Queryable::new(import(&dir.join("t.gltf")).unwrap());
    let grey = sylva_engine::shading::srgb_to_linear(128.0 / 255.0);
    for (x, expected) in [(0.125, Vec3A::X), (0.875, Vec3A::splat(grey))] {
        let e = shade_at(&q, x, 0.5).emission;
        assert!(
            (e - expected).abs().max_element() < 1e-4,
            "x = {x}: {e} against {expected}"
        );
    }
    assert_eq!(shade_at(&q, 2.5, 0.5).emission, Vec3A::ZERO);
    assert!(q.scene.shaders[1].emission.is_none());

    for (bad, place) in [
        (
            r#"{"emissiveFactor":[1,-1,0]}"#,
            "materials[0].emissiveFactor",
        ),
        (
            r#"{"emissiveFactor":[1,1,1],"extensions":{"KHR_materials_emissive_strength":{"emissiveStrength":-2}}}"#,
            "emissiveStrength",
        ),
    ] {
        let text = quads_gltf(&format!("[{bad},{plain},{plain},{plain},{plain}]"), "");
        let dir = scratch("emissive-bad", &[("b.gltf", text.as_bytes())]);
        let error = import(&dir.join("b.gltf")).unwrap_err().to_string();
        assert!(error.contains("b.gltf") && error.contains(place), "{error}");
    }
}

#[test]
fn diffuse_transmission_lets_light_through_from_behind_clamped_and_textured() {
    // KHR_materials_diffuse_transmission (the gltf crate does not parse it): quad 0
    // transmits 0.4 of a yellow-green tint; quad 1 asks for 1.5 (clamped to 1: it then
    // reflects nothing); quad 2 gets its factor 0.8 halved by its factor texture's alpha;
    // quad 3 is opaque.
    let mut png = Vec::new();
    image::RgbaImage::from_raw(1, 1, vec![255, 255, 255, 128])
        .unwrap()
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    let ext = |body: &str| {
        format!(
            r#"{{"pbrMetallicRoughness":{{"baseColorFactor":[0.6,0.5,0.4,1]}},"extensions":{{"KHR_materials_diffuse_transmission":{body}}}}}"#
        )
    };
    let materials = format!(
        "[{},{},{},{},{}]",
        ext(r#"{"diffuseTransmissionFactor":0.4,"diffuseTransmissionColorFactor":[0.9,0.8,0.3]}"#),
        ext(r#"{"diffuseTransmissionFactor":1.5}"#),
        ext(r#"{"diffuseTransmissionFactor":0.8,"diffuseTransmissionTexture":{"index":0}}"#),
        r#"{"pbrMetallicRoughness":{"baseColorFactor":[0.6,0.5,0.4,1]}}"#,
        r#"{}"#
    );
    let extra = format!(
        r#","textures":[{{"source":0}}],"images":[{{"uri":"data:image/png;base64,{}"}}]"#,
        base64(&png)
    );
    let text = quads_gltf(&materials, &extra);
    let dir = scratch("transmission", &[("t.gltf", text.as_bytes())]);
    let mut q = Queryable::new(import(&dir.join("t.gltf")).unwrap());
    let transmission = |i: usize| q.scene.shaders[i].transmission.clone();
    assert_eq!(transmission(0).unwrap().factor, 0.4);
    assert_eq!(transmission(1).unwrap().factor, 1.0);
    assert!(transmission(3).is_none());
    let (irradiance, theta) = (Vec3::new(3.0, 2.0, 1.0), 0.5f32);
    let lit = |q: &mut Queryable, behind: bool| {
        let z = if behind { -theta.cos() } else { theta.cos() };
        q.lights = LightSet {
            directional: vec![sylva_engine::light::DirectionalLight {
                direction: Vec3::new(theta.sin(), 0.0, z),
                irradiance,
            }],
            ..Default::default()
        };
        (0..4)
            .map(|i| Vec3::from(shade_at(q, 2.0 * i as f32 + 0.5, 0.5).radiance))
            .collect::<Vec<_>>()
    };
    let behind = lit(&mut q, true);
    let front = lit(&mut q, false);
    let e = irradiance * theta.cos() / std::f32::consts::PI;
    let base = Vec3::new(0.6, 0.5, 0.4);
    let grey = 128.0 / 255.0;
    let expected_behind = [
        0.4 * Vec3::new(0.9, 0.8, 0.3) * e,
        e,
        0.8 * grey * e,
        Vec3::ZERO,
    ];
    let expected_front = [
        0.6 * base * e,
        Vec3::ZERO,
        (1.0 - 0.8 * grey) * base * e,
        base * e,
    ];
    for i in 0..4 {
        for (seen, expected) in [
            (behind[i], expected_behind[i]),
            (front[i], expected_front[i]),
        ] {
            assert!(
                (seen - expected).abs().max_element() < 1e-4,
                "quad {i}: {seen} against {expected}"
            );
        }
    }

    let plain = r#"{}"#;
    let bad = ext(r#"{"diffuseTransmissionFactor":0.5,"diffuseTransmissionColorFactor":[1,2]}"#);
    let text = quads_gltf(&format!("[{bad},{plain},{plain},{plain},{plain}]"), "");
    let dir = scratch("transmission-bad", &[("b.gltf", text.as_bytes())]);
    let error = import(&dir.join("b.gltf")).unwrap_err().to_string();
    assert!(
        error.contains("b.gltf")
            && error.contains("KHR_materials_diffuse_transmission.diffuseTransmissionColorFactor"),
        "{error}"
    );
}

/// A glTF in the manner of Khronos' InterpolationTest: three triangle nodes, the first
/// under a parent whose translation is animated with STEP, the second rotated with
/// LINEAR, the third scaled with CUBICSPLINE, all on keys at 0, 1 and 2 s.
fn animated_gltf() -> String {
    let floats = |v: &[f32]| -> Vec<u8> { v.iter().flat_map(|f| f.to_le_bytes()).collect() };
    let half = std::f32::consts::FRAC_1_SQRT_2;
    let parts: [Vec<u8>; 5] = [
        floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]),
        floats(&[0.0, 1.0, 2.0]),
        floats(&[0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 2.0, 3.0, 0.0]),
        // Identity, 90° about Y, 180° about Y.
        floats(&[0.0, 0.0, 0.0, 1.0, 0.0, half, 0.0, half, 0.0, 1.0, 0.0, 0.0]),
        // (in-tangent, value, out-tangent) per key.
        floats(&[
            0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, //
            0.0, 2.0, 0.0, 2.0, 2.0, 2.0, 0.0, 0.0, 1.0, //
            0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0,
        ]),
    ];
    let mut bytes = Vec::new();
    let mut views = Vec::new();
    for part in &parts {
        views.push(format!(
            r#"{{"buffer":0,"byteOffset":{},"byteLength":{}}}"#,
            bytes.len(),
            part.len()
        ));
        bytes.extend(part);
    }
    format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0,2,3]}}],
"nodes":[{{"children":[1],"translation":[0,0,-1]}},{{"mesh":0,"translation":[0,0.5,0]}},{{"mesh":0,"translation":[4,0,0]}},{{"mesh":0,"translation":[-4,0,0]}}],
"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
"animations":[
 {{"channels":[{{"sampler":0,"target":{{"node":0,"path":"translation"}}}}],"samplers":[{{"input":1,"interpolation":"STEP","output":2}}]}},
 {{"channels":[{{"sampler":0,"target":{{"node":2,"path":"rotation"}}}}],"samplers":[{{"input":1,"interpolation":"LINEAR","output":3}}]}},
 {{"channels":[{{"sampler":0,"target":{{"node":3,"path":"scale"}}}}],"samplers":[{{"input":1,"interpolation":"CUBICSPLINE","output":4}}]}}],
"buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{}"}}],
"bufferViews":[{}],
"accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
 {{"bufferView":1,"componentType":5126,"count":3,"type":"SCALAR","min":[0],"max":[2]}},
 {{"bufferView":2,"componentType":5126,"count":3,"type":"VEC3"}},
 {{"bufferView":3,"componentType":5126,"count":3,"type":"VEC4"}},
 {{"bufferView":4,"componentType":5126,"count":9,"type":"VEC3"}}]}}"#,
        bytes.len(),
        base64(&bytes),
        views.join(",")
    )
}

#[test]
fn animation_channels_move_their_nodes_as_the_gltf_spec_says() {
    use bevy_ecs::prelude::*;
    use sylva_engine::components::Transform;
    use sylva_engine::sway::AnimationClock;
    use sylva_systems::{NodeAnimationPlayer, TopLevelState, frame_schedule, init_render_world};
    let text = animated_gltf();
    let scene = sylva_scenes::gltf::import_slice(text.as_bytes(), Path::new("anim.gltf")).unwrap();
    let animation = scene.animation.clone().expect("the file has animations");
    assert_eq!(animation.channels.len(), 3);
    assert_eq!(animation.duration(), 2.0);
    let world_at = |t: f32| animation.world_transforms(t);
    let close = |a: Vec3A, b: Vec3| (a - Vec3A::from(b)).length() < 1e-5;

    // STEP: the parent's key 0 until t = 1, then key 1; the child rides on it.
    assert!(close(
        world_at(0.99)[1].translation,
        Vec3::new(0.0, 0.5, 0.0)
    ));
    assert!(close(
        world_at(1.0)[1].translation,
        Vec3::new(2.0, 0.5, 0.0)
    ));
    assert!(close(
        world_at(9.0)[1].translation,
        Vec3::new(2.0, 3.5, 0.0)
    ));
    // LINEAR rotation: halfway between 0° and 90° about Y at t = 0.5.
    let (_, rotation, _) = world_at(0.5)[2].to_scale_rotation_translation();
    let expected = glam::Quat::from_rotation_y(std::f32::consts::FRAC_PI_4);
    assert!(1.0 - rotation.dot(expected).abs() < 1e-6, "{rotation}");
    // CUBICSPLINE scale at t = 0.25 (s = 0.25, Δt = 1): the Hermite formula with the
    // out-tangent of key 0 and the in-tangent of key 1.
    let s = 0.25f32;
    let (s2, s3) = (s * s, s * s * s);
    let p0 = Vec3::splat(1.0);
    let b0 = Vec3::new(1.0, 0.0, 0.0);
    let a1 = Vec3::new(0.0, 2.0, 0.0);
    let p1 = Vec3::splat(2.0);
    let scale = p0 * (2.0 * s3 - 3.0 * s2 + 1.0)
        + b0 * (s3 - 2.0 * s2 + s)
        + p1 * (-2.0 * s3 + 3.0 * s2)
        + a1 * (s3 - s2);
    let (got, _, _) = world_at(0.25)[3].to_scale_rotation_translation();
    assert!((got - scale).length() < 1e-5, "{got} vs {scale}");

    // In a world: the three triangles follow their nodes frame by frame, and only the
    // top level's refit runs after the first build.
    let build = scene.into_scene(&CameraChoice::First).unwrap();
    let (animation, bound) = build.node_animation.clone().expect("bound instances");
    assert_eq!(bound.len(), 3, "the child of the animated parent moves too");
    let mut world = World::new();
    init_render_world(&mut world, 1).unwrap();
    let mut build = build;
    build.camera.width = 16;
    build.camera.height = 12;
    let spawned = sylva_scenes::spawn(&mut world, build);
    let instances = bound
        .iter()
        .map(|&(plant, node, local)| (spawned.plants[plant], node, local))
        .collect();
    world.insert_resource(NodeAnimationPlayer {
        animation: animation.clone(),
        instances,
    });
    let mut schedule = frame_schedule();
    for frame in 0..6 {
        world.resource_mut::<AnimationClock>().frame_seconds = if frame == 0 { 0.0 } else { 0.25 };
        schedule.run(&mut world);
        let time = world.resource::<AnimationClock>().time as f32;
        let nodes = animation.world_transforms(time);
        for &(plant, node, _) in &bound {
            let t = world.get::<Transform>(spawned.plants[plant]).unwrap();
            assert!(
                close(nodes[node].translation, t.translation),
                "frame {frame}"
            );
        }
    }
    let state = world.resource::<TopLevelState>();
    assert_eq!(state.rebuilds, 1, "one build, then refits");
    assert_eq!(state.refits, 5);
}

/// The spec's value of a sampler at `time`, computed here from the file's keys as read by
/// the gltf crate (not by the importer): STEP, LINEAR (rotations: normalised slerp) and
/// CUBICSPLINE (Hermite with the tangents scaled by the key interval).
fn spec_value(
    times: &[f32],
    outputs: &[glam::Vec4],
    interpolation: gltf::animation::Interpolation,
    rotation: bool,
    time: f32,
) -> glam::Vec4 {
    use gltf::animation::Interpolation::*;
    let cubic = interpolation == CubicSpline;
    let value = |k: usize| {
        if cubic {
            outputs[3 * k + 1]
        } else {
            outputs[k]
        }
    };
    let last = times.len() - 1;
    if time <= times[0] {
        return value(0);
    }
    if time >= times[last] {
        return value(last);
    }
    let k = (0..last).rev().find(|&k| times[k] <= time).unwrap();
    let dt = times[k + 1] - times[k];
    let s = (time - times[k]) / dt;
    match interpolation {
        Step => value(k),
        Linear if rotation => {
            let a = glam::Quat::from_vec4(value(k)).normalize();
            let b = glam::Quat::from_vec4(value(k + 1)).normalize();
            glam::Vec4::from(a.slerp(b, s))
        }
        Linear => value(k) * (1.0 - s) + value(k + 1) * s,
        CubicSpline => {
            let (s2, s3) = (s * s, s * s * s);
            let v = value(k) * (2.0 * s3 - 3.0 * s2 + 1.0)
                + outputs[3 * k + 2] * dt * (s3 - 2.0 * s2 + s)
                + value(k + 1) * (-2.0 * s3 + 3.0 * s2)
                + outputs[3 * (k + 1)] * dt * (s3 - s2);
            if rotation { v.normalize() } else { v }
        }
    }
}

#[test]
fn interpolation_test_moves_every_node_as_its_sampler_says() {
    use gltf::animation::util::ReadOutputs;
    let path = model("InterpolationTest");
    let scene = import(&path).unwrap();
    let animation = scene.animation.expect("InterpolationTest is animated");
    let (document, buffers, _) = gltf::import(&path).unwrap();
    let mut checked = std::collections::BTreeSet::new();
    for channel in document
        .animations()
        .flat_map(|a| a.channels().collect::<Vec<_>>())
    {
        let reader = channel.reader(|b| Some(&buffers[b.index()]));
        let times: Vec<f32> = reader.read_inputs().unwrap().collect();
        let (outputs, rotation): (Vec<glam::Vec4>, bool) = match reader.read_outputs().unwrap() {
            ReadOutputs::Translations(v) | ReadOutputs::Scales(v) => {
                (v.map(|p| Vec3::from(p).extend(0.0)).collect(), false)
            }
            ReadOutputs::Rotations(v) => (v.into_f32().map(glam::Vec4::from).collect(), true),
            ReadOutputs::MorphTargetWeights(_) => continue,
        };
        let node = channel.target().node().index();
        let interpolation = channel.sampler().interpolation();
        let property = channel.target().property();
        // At every key, halfway and a quarter between keys, and past both ends.
        let mut samples = vec![times[0] - 0.5, times[times.len() - 1] + 0.5];
        for w in times.windows(2) {
            samples.extend([
                w[0],
                w[0] + 0.25 * (w[1] - w[0]),
                w[0] + 0.5 * (w[1] - w[0]),
            ]);
        }
        for time in samples {
            let expected = spec_value(&times, &outputs, interpolation, rotation, time);
            // Every InterpolationTest node is a root: its world transform is its pose.
            let (scale, turn, translation) =
                animation.world_transforms(time)[node].to_scale_rotation_translation();
            let got = match property {
                gltf::animation::Property::Translation => translation.extend(0.0),
                gltf::animation::Property::Scale => scale.extend(0.0),
                _ => glam::Vec4::from(turn),
            };
            let error = if rotation {
                1.0 - got.dot(expected).abs()
            } else {
                (got - expected).length()
            };
            assert!(
                error < 1e-4,
                "node {node} {property:?} {interpolation:?} at {time}: {got} vs {expected}"
            );
        }
        checked.insert(format!("{property:?} {interpolation:?}"));
    }
    // Every sampler kind on every property the file has.
    assert_eq!(checked.len(), 9, "{checked:?}");
}

#[test]
fn box_animated_moves_the_child_with_its_parent_and_only_refits_the_top_level() {
    use bevy_ecs::prelude::*;
    use sylva_engine::components::Transform;
    use sylva_engine::sway::AnimationClock;
    use sylva_systems::{NodeAnimationPlayer, TopLevelState, frame_schedule, init_render_world};
    let scene = import(&model("BoxAnimated")).unwrap();
    let animation = scene.animation.clone().unwrap();
    assert_eq!(animation.channels.len(), 2);
    let mut build = scene.into_scene(&CameraChoice::First).unwrap();
    let (animation, bound) = build.node_animation.take().unwrap();
    // The inner box (node 2, rotated) sits under node 1 under node 0 (translated): it
    // is bound; the outer box (node 3) does not move and is not.
    assert_eq!(bound.iter().map(|b| b.1).collect::<Vec<_>>(), vec![2]);
    build.camera.width = 16;
    build.camera.height = 12;
    let mut world = World::new();
    init_render_world(&mut world, 1).unwrap();
    let spawned = sylva_scenes::spawn(&mut world, build);
    let inner = spawned.plants[bound[0].0];
    world.insert_resource(NodeAnimationPlayer {
        animation: animation.clone(),
        instances: vec![(inner, bound[0].1, bound[0].2)],
    });
    let mut schedule = frame_schedule();
    let mut heights = Vec::new();
    for frame in 0..9 {
        world.resource_mut::<AnimationClock>().frame_seconds = if frame == 0 { 0.0 } else { 0.5 };
        schedule.run(&mut world);
        let time = world.resource::<AnimationClock>().time as f32;
        let t = *world.get::<Transform>(inner).unwrap();
        let expected = animation.world_transforms(time)[2];
        assert!((Vec3A::from(t.translation) - expected.translation).length() < 1e-5);
        heights.push(t.translation.y);
    }
    // The parent's translation channel lifts the inner box to 2.52 m and, by its last
    // key at 3.71 s, back down; it stays there after the end.
    let top = heights.iter().copied().fold(0.0f32, f32::max);
    assert!(
        top > 2.5 && heights[0] < 1e-6 && heights[8] < 1e-6,
        "{heights:?}"
    );
    // Only transforms change: after the first build every frame refits, or rebuilds
    // because the refitted tree degraded past the refit limit (two boxes passing
    // through each other), never because the instances changed.
    let state = world.resource::<TopLevelState>();
    assert_eq!(state.rebuilds - state.degraded_rebuilds, 1, "{state:?}");
    assert_eq!(state.refits + state.degraded_rebuilds, 8, "{state:?}");
}

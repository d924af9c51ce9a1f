//! glTF 2.0 / GLB import: meshes become geometry, every node that references a mesh
//! becomes an instance (and `EXT_mesh_gpu_instancing` multiplies it), materials become
//! shaders, perspective cameras become views.
//!
//! Materials: base colour factor × base colour texture (sRGB, the sampler's wrap modes,
//! `KHR_texture_transform`); `alphaMode` OPAQUE ignores alpha, MASK cuts holes below
//! `alphaCutoff` (default 0.5), and BLEND is treated as MASK at 0.5 (a ray tracer without
//! sorting has no blending; documented and tested). Emission: `emissiveFactor` ×
//! `KHR_materials_emissive_strength` × `emissiveTexture`, seen by camera rays (not a
//! light source). `KHR_materials_diffuse_transmission` makes thin surfaces translucent
//! (parsed from the raw JSON: the gltf crate does not know it). `doubleSided: false` surfaces are
//! invisible from behind, where the front follows glTF's rule (winding, flipped by a
//! negative determinant). Primitives without normals get flat normals.
//!
//! Bad input never panics: truncated files, missing buffers, indices out of range and
//! undecodable images are errors naming the file and the glTF path; NaN/Inf vertices are
//! dropped with a warning that counts them; singular instance transforms are left out
//! and counted.

use crate::species::SpeciesModel;
use crate::{Plant, SceneBuild, SceneError, Species};
use glam::{Affine3A, Mat4, Quat, Vec2, Vec3, Vec3A, Vec4};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;
use sylva_engine::bvh::BuildParams;
use sylva_engine::camera::Camera;
use sylva_engine::components::Transform;
use sylva_engine::geometry::{Geometry, GeometryLibrary};
use sylva_engine::light::{DirectionalLight, SkyLight};
use sylva_engine::math::Aabb;
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::node_animation::{Channel, Interpolation, NodeAnimation, NodeTrs, Property};
use sylva_engine::shading::{
    Emission, Shader, ShaderId, Texture, Transmission, UvTransform, WrapMode,
};

/// Largest texture edge accepted (checked before decoding).
pub const MAX_TEXTURE_EDGE: u32 = 16_384;

/// Why a glTF file could not be imported.
#[derive(Debug, thiserror::Error)]
#[error("{}: {}{message}", path.display(), location.as_deref().map(|l| format!("{l}: ")).unwrap_or_default())]
pub struct GltfError {
    /// The file.
    pub path: PathBuf,
    /// The glTF JSON path of the offending part (`meshes[2].primitives[0].indices`).
    pub location: Option<String>,
    /// What is wrong.
    pub message: String,
}

/// One mesh of the file: its primitives merged, triangles naming shaders by material
/// slot (the last slot is glTF's default material).
#[derive(Clone, Debug)]
pub struct GltfMesh {
    /// The mesh's name (or `mesh N`).
    pub name: String,
    /// The triangles.
    pub mesh: TriangleMesh,
}

/// A placed copy of a mesh.
#[derive(Clone, Debug, PartialEq)]
pub struct GltfInstance {
    /// Index into [`GltfScene::meshes`].
    pub mesh: usize,
    /// Object → world.
    pub transform: Affine3A,
    /// The node's name (or `nodes[N]`).
    pub node: String,
    /// The node's index.
    pub node_index: usize,
    /// The transform under the node (GPU instancing's; identity otherwise).
    pub local: Affine3A,
}

/// A perspective camera and where its node puts it.
#[derive(Clone, Debug, PartialEq)]
pub struct GltfCamera {
    /// The camera's name (or `cameras[N]`).
    pub name: String,
    /// Vertical field of view in radians.
    pub yfov: f32,
    /// Width / height, when the file gives it.
    pub aspect_ratio: Option<f32>,
    /// Camera → world (looks along −Z, +Y up).
    pub transform: Affine3A,
}

/// What an import counted and left out.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ImportReport {
    /// Vertices with a NaN or infinite coordinate.
    pub non_finite_vertices: usize,
    /// Triangles dropped because they used such a vertex.
    pub dropped_triangles: usize,
    /// Instances with a singular or non-finite transform (left out).
    pub singular_instances: usize,
    /// Primitives of point or line modes (not surfaces; left out).
    pub skipped_primitives: usize,
    /// Orthographic cameras (not supported; left out).
    pub orthographic_cameras: usize,
    /// Animation channels of morph-target weights (not supported; left out).
    pub weight_channels: usize,
    /// Emissive and diffuse-transmission textures on another UV set than the one their
    /// material's meshes keep (the base colour texture's): left out, their factors
    /// still apply.
    pub textures_left_out: usize,
}

/// An imported file as plain data.
#[derive(Clone, Debug)]
pub struct GltfScene {
    /// The file.
    pub path: PathBuf,
    /// Meshes.
    pub meshes: Vec<GltfMesh>,
    /// Shaders by material slot; the last one is the default material.
    pub shaders: Vec<Shader>,
    /// Mesh instances of the default scene.
    pub instances: Vec<GltfInstance>,
    /// Perspective cameras of the default scene, in node order.
    pub cameras: Vec<GltfCamera>,
    /// The file's animations of node translation, rotation and scale, played together;
    /// `None` without any.
    pub animation: Option<NodeAnimation>,
    /// What was left out.
    pub report: ImportReport,
}

struct Importer<'a> {
    path: &'a Path,
    document: gltf::Document,
    buffers: Vec<gltf::buffer::Data>,
}

impl Importer<'_> {
    fn error(&self, location: impl Into<Option<String>>, message: impl Into<String>) -> GltfError {
        GltfError {
            path: self.path.to_path_buf(),
            location: location.into(),
            message: message.into(),
        }
    }

    fn buffer_data<'s>(&'s self) -> impl Clone + Fn(gltf::Buffer<'_>) -> Option<&'s [u8]> {
        move |b: gltf::Buffer<'_>| self.buffers.get(b.index()).map(|d| &d.0[..])
    }
}

/// Imports a `.gltf` or `.glb` file.
pub fn import(path: &Path) -> Result<GltfScene, GltfError> {
    let bytes = std::fs::read(path).map_err(|e| GltfError {
        path: path.to_path_buf(),
        location: None,
        message: format!("cannot read: {e}"),
    })?;
    import_slice(&bytes, path)
}

/// Imports glTF or GLB bytes; `path` names them in errors and anchors relative URIs.
pub fn import_slice(bytes: &[u8], path: &Path) -> Result<GltfScene, GltfError> {
    let fail = |location: Option<String>, message: String| GltfError {
        path: path.to_path_buf(),
        location,
        message,
    };
    // gltf-json 1.4's validation indexes a primitive's POSITION accessor before checking
    // it exists and panics on such files: check that first, and keep any other panic in
    // the dependency from escaping as one.
    let malformed = || fail(None, "malformed glTF (the gltf crate failed on it)".into());
    let unchecked = std::panic::catch_unwind(|| gltf::Gltf::from_slice_without_validation(bytes))
        .map_err(|_| malformed())?
        .map_err(|e| fail(None, format!("not a valid glTF/GLB file: {e}")))?;
    let root = unchecked.document.as_json();
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, primitive) in mesh.primitives.iter().enumerate() {
            for (semantic, accessor) in &primitive.attributes {
                if accessor.value() >= root.accessors.len() {
                    return Err(fail(
                        Some(format!(
                            "meshes[{m}].primitives[{p}].attributes.{semantic:?}"
                        )),
                        format!(
                            "accessor {} does not exist ({} accessors)",
                            accessor.value(),
                            root.accessors.len()
                        ),
                    ));
                }
            }
        }
    }
    let gltf = std::panic::catch_unwind(|| gltf::Gltf::from_slice(bytes))
        .map_err(|_| malformed())?
        .map_err(|e| fail(None, format!("not a valid glTF/GLB file: {e}")))?;
    let base = path.parent().unwrap_or(Path::new("."));
    for buffer in gltf.document.buffers() {
        if let gltf::buffer::Source::Uri(uri) = buffer.source()
            && !uri.starts_with("data:")
        {
            let file = base.join(uri);
            if !file.is_file() {
                return Err(fail(
                    Some(format!("buffers[{}].uri", buffer.index())),
                    format!("buffer file '{}' not found", file.display()),
                ));
            }
        }
    }
    let gltf::Gltf { document, blob } = gltf;
    let buffers = gltf::import_buffers(&document, Some(base), blob)
        .map_err(|e| fail(Some("buffers".into()), e.to_string()))?;
    let importer = Importer {
        path,
        document,
        buffers,
    };
    let mut report = ImportReport::default();
    let shaders = materials(&importer, base, &mut report)?;
    let default_slot = shaders.len() as u32 - 1;
    let meshes = importer
        .document
        .meshes()
        .map(|m| mesh(&importer, &mut report, &m, default_slot))
        .collect::<Result<Vec<_>, _>>()?;
    let (instances, cameras) = nodes(&importer, &mut report)?;
    let animation = animation(&importer, &mut report)?;
    if report.weight_channels > 0 {
        tracing::warn!(
            "{}: left out {} morph-target weight animation channels",
            path.display(),
            report.weight_channels
        );
    }
    if report.non_finite_vertices > 0 {
        tracing::warn!(
            "{}: dropped {} NaN/Inf vertices ({} triangles)",
            path.display(),
            report.non_finite_vertices,
            report.dropped_triangles
        );
    }
    if report.textures_left_out > 0 {
        tracing::warn!(
            "{}: left out {} emissive or transmission textures on another UV set than \
             their base colour texture (their factors still apply)",
            path.display(),
            report.textures_left_out
        );
    }
    if report.singular_instances > 0 {
        tracing::warn!(
            "{}: left out {} instances with singular transforms",
            path.display(),
            report.singular_instances
        );
    }
    Ok(GltfScene {
        path: path.to_path_buf(),
        meshes,
        shaders,
        instances,
        cameras,
        animation,
        report,
    })
}

/// The node hierarchy with its rest poses and every animation's TRS channels, checked:
/// key times finite and not decreasing, one output per key (three for CUBICSPLINE).
fn animation(
    importer: &Importer,
    report: &mut ImportReport,
) -> Result<Option<NodeAnimation>, GltfError> {
    use gltf::animation::util::ReadOutputs;
    let document = &importer.document;
    if document.animations().len() == 0 {
        return Ok(None);
    }
    let count = document.nodes().len();
    let mut parents = vec![None; count];
    let mut rest = Vec::with_capacity(count);
    for node in document.nodes() {
        for child in node.children() {
            parents[child.index()] = Some(node.index());
        }
        let (t, r, s) = node.transform().decomposed();
        rest.push(NodeTrs {
            translation: Vec3::from(t),
            rotation: glam::Quat::from_array(r).normalize(),
            scale: Vec3::from(s),
        });
    }
    let mut channels = Vec::new();
    for animation in document.animations() {
        for channel in animation.channels() {
            let location = format!(
                "animations[{}].channels[{}]",
                animation.index(),
                channel.index()
            );
            let reader = channel.reader(importer.buffer_data());
            let times: Vec<f32> = reader
                .read_inputs()
                .ok_or_else(|| {
                    importer.error(location.clone(), "the sampler's input cannot be read")
                })?
                .collect();
            if times.is_empty()
                || times.iter().any(|t| !t.is_finite())
                || times.windows(2).any(|w| w[1] < w[0])
            {
                return Err(importer.error(location, "key times must be finite and not decreasing"));
            }
            let outputs = reader.read_outputs().ok_or_else(|| {
                importer.error(location.clone(), "the sampler's output cannot be read")
            })?;
            let (property, values): (Property, Vec<glam::Vec4>) = match outputs {
                ReadOutputs::Translations(v) => (
                    Property::Translation,
                    v.map(|p| Vec3::from(p).extend(0.0)).collect(),
                ),
                ReadOutputs::Scales(v) => (
                    Property::Scale,
                    v.map(|p| Vec3::from(p).extend(0.0)).collect(),
                ),
                ReadOutputs::Rotations(v) => (
                    Property::Rotation,
                    v.into_f32().map(glam::Vec4::from).collect(),
                ),
                ReadOutputs::MorphTargetWeights(_) => {
                    report.weight_channels += 1;
                    continue;
                }
            };
            let interpolation = match channel.sampler().interpolation() {
                gltf::animation::Interpolation::Step => Interpolation::Step,
                gltf::animation::Interpolation::Linear => Interpolation::Linear,
                gltf::animation::Interpolation::CubicSpline => Interpolation::CubicSpline,
            };
            let per_key = if interpolation == Interpolation::CubicSpline {
                3
            } else {
                1
            };
            if values.len() != per_key * times.len() || values.iter().any(|v| !v.is_finite()) {
                return Err(importer.error(
                    location,
                    format!(
                        "{} finite output values expected for {} keys, {} found",
                        per_key * times.len(),
                        times.len(),
                        values.len()
                    ),
                ));
            }
            channels.push(Channel {
                node: channel.target().node().index(),
                property,
                times,
                values,
                interpolation,
            });
        }
    }
    Ok((!channels.is_empty()).then_some(NodeAnimation {
        parents,
        rest,
        channels,
    }))
}

fn wrap_mode(mode: gltf::texture::WrappingMode) -> WrapMode {
    match mode {
        gltf::texture::WrappingMode::ClampToEdge => WrapMode::ClampToEdge,
        gltf::texture::WrappingMode::MirroredRepeat => WrapMode::MirroredRepeat,
        gltf::texture::WrappingMode::Repeat => WrapMode::Repeat,
    }
}

/// The texture coordinate set a texture reference reads (its transform may override it).
fn texture_set(info: &gltf::texture::Info) -> u32 {
    info.texture_transform()
        .and_then(|t| t.tex_coord())
        .unwrap_or(info.tex_coord())
}

/// The UV set a material's meshes keep: its base colour texture's, else its emissive
/// texture's, else 0. Sylva keeps one set per mesh.
fn material_uv_set(material: &gltf::Material) -> u32 {
    let base = material.pbr_metallic_roughness().base_color_texture();
    base.or_else(|| material.emissive_texture())
        .map_or(0, |info| texture_set(&info))
}

/// A texture reference decoded once per image, with its sampler's wrap modes and its
/// `KHR_texture_transform`.
fn texture_of(
    importer: &Importer,
    base: &Path,
    textures: &mut [Option<Arc<Texture>>],
    info: &gltf::texture::Info,
    role: &str,
) -> Result<(Arc<Texture>, Option<UvTransform>), GltfError> {
    let transform = info.texture_transform().map(|t| UvTransform {
        offset: Vec2::from(t.offset()),
        rotation: t.rotation(),
        scale: Vec2::from(t.scale()),
    });
    Ok((
        decoded(importer, base, textures, &info.texture(), role)?,
        transform,
    ))
}

/// A texture's image decoded once per image, with the sampler's wrap modes.
fn decoded(
    importer: &Importer,
    base: &Path,
    textures: &mut [Option<Arc<Texture>>],
    texture: &gltf::Texture,
    role: &str,
) -> Result<Arc<Texture>, GltfError> {
    let image = texture.source();
    let decoded = match &textures[image.index()] {
        Some(t) => t.clone(),
        None => {
            let t = Arc::new(decode_image(importer, &image, base, role)?);
            textures[image.index()] = Some(t.clone());
            t
        }
    };
    let sampler = texture.sampler();
    Ok(Arc::new((*decoded).clone().with_wrap(
        wrap_mode(sampler.wrap_s()),
        wrap_mode(sampler.wrap_t()),
    )))
}

/// A texture reference in an extension the gltf crate does not parse (`{"index",
/// "texCoord", "extensions": {"KHR_texture_transform": …}}`): the texture, its UV set
/// and its transform; malformed references are errors at `at`.
fn raw_texture_ref<'a>(
    importer: &'a Importer,
    value: &gltf::json::Value,
    at: &str,
) -> Result<(gltf::Texture<'a>, u32, Option<UvTransform>), GltfError> {
    let bad = |what: &str| importer.error(at.to_string(), what.to_string());
    let index = value
        .get("index")
        .and_then(|i| i.as_u64())
        .ok_or_else(|| bad("a texture reference needs an integer \"index\""))?;
    let texture = importer
        .document
        .textures()
        .nth(index as usize)
        .ok_or_else(|| bad(&format!("texture {index} does not exist")))?;
    let mut set = value.get("texCoord").and_then(|t| t.as_u64()).unwrap_or(0) as u32;
    let transform = match value.pointer("/extensions/KHR_texture_transform") {
        Some(t) => {
            let pair = |key: &str, default: [f32; 2]| -> Vec2 {
                t.get(key)
                    .and_then(|v| v.as_array())
                    .filter(|a| a.len() == 2)
                    .map_or(Vec2::from(default), |a| {
                        Vec2::new(
                            a[0].as_f64().unwrap_or(default[0] as f64) as f32,
                            a[1].as_f64().unwrap_or(default[1] as f64) as f32,
                        )
                    })
            };
            if let Some(coord) = t.get("texCoord").and_then(|c| c.as_u64()) {
                set = coord as u32;
            }
            Some(UvTransform {
                offset: pair("offset", [0.0, 0.0]),
                rotation: t.get("rotation").and_then(|r| r.as_f64()).unwrap_or(0.0) as f32,
                scale: pair("scale", [1.0, 1.0]),
            })
        }
        None => None,
    };
    Ok((texture, set, transform))
}

/// `KHR_materials_diffuse_transmission` (the gltf crate does not parse it): factor ×
/// the factor texture's alpha, colour factor × colour texture. Factors outside 0 ..= 1
/// are clamped with a warning naming the material, so reflectance plus transmittance
/// stays at most 1; textures on another UV set than the mesh keeps are left out and
/// counted.
fn transmission(
    importer: &Importer,
    base: &Path,
    textures: &mut [Option<Arc<Texture>>],
    material: &gltf::Material,
    report: &mut ImportReport,
) -> Result<Option<Transmission>, GltfError> {
    const NAME: &str = "KHR_materials_diffuse_transmission";
    let Some(value) = material.extension_value(NAME) else {
        return Ok(None);
    };
    let index = material.index().unwrap_or(0);
    let name = material.name().unwrap_or("");
    let at = format!("materials[{index}].extensions.{NAME}");
    let number = |key: &str, default: f64| -> Result<f32, GltfError> {
        match value.get(key) {
            None => Ok(default as f32),
            Some(v) => v.as_f64().map(|x| x as f32).ok_or_else(|| {
                importer.error(format!("{at}.{key}"), "must be a number".to_string())
            }),
        }
    };
    let factor = number("diffuseTransmissionFactor", 0.0)?;
    let color = match value.get("diffuseTransmissionColorFactor") {
        None => Vec3::ONE,
        Some(v) => v
            .as_array()
            .filter(|a| a.len() == 3)
            .and_then(|a| {
                let c: Option<Vec<f32>> = a.iter().map(|x| x.as_f64().map(|x| x as f32)).collect();
                c.map(|c| Vec3::new(c[0], c[1], c[2]))
            })
            .ok_or_else(|| {
                importer.error(
                    format!("{at}.diffuseTransmissionColorFactor"),
                    "must be an array of three numbers".to_string(),
                )
            })?,
    };
    let (mut transmission, clamped) = Transmission::new(factor, color).clamped();
    if clamped {
        tracing::warn!(
            "{}: material '{name}' ({at}): diffuse transmission factor {factor} and colour \
             {color} clamped to 0..1 so that reflected plus transmitted light stays at \
             most what arrives",
            importer.path.display()
        );
    }
    let uv_set = material_uv_set(material);
    for key in [
        "diffuseTransmissionTexture",
        "diffuseTransmissionColorTexture",
    ] {
        let Some(reference) = value.get(key) else {
            continue;
        };
        let (texture, set, transform) =
            raw_texture_ref(importer, reference, &format!("{at}.{key}"))?;
        if set != uv_set {
            report.textures_left_out += 1;
            continue;
        }
        let role = format!("{key} of material '{name}' (materials[{index}])");
        let decoded = decoded(importer, base, textures, &texture, &role)?;
        if key == "diffuseTransmissionTexture" {
            transmission.factor_texture = Some(decoded);
            transmission.factor_uv_transform = transform;
        } else {
            transmission.color_texture = Some(decoded);
            transmission.uv_transform = transform;
        }
    }
    Ok((transmission.factor > 0.0).then_some(transmission))
}

/// Shaders for every material plus glTF's default material (white, opaque, single-sided).
fn materials(
    importer: &Importer,
    base: &Path,
    report: &mut ImportReport,
) -> Result<Vec<Shader>, GltfError> {
    let mut shaders = Vec::new();
    let mut textures: Vec<Option<Arc<Texture>>> = vec![None; importer.document.images().len()];
    let materials: Vec<_> = importer.document.materials().collect();
    for material in materials {
        let index = material.index().unwrap_or(0);
        let name = material.name().unwrap_or("").to_string();
        let pbr = material.pbr_metallic_roughness();
        let [r, g, b, a] = pbr.base_color_factor();
        let mut shader = Shader::color(ShaderId(index as u32), Vec3::new(r, g, b));
        shader.double_sided = material.double_sided();
        if let Some(info) = &pbr.base_color_texture() {
            let role = format!("baseColorTexture of material '{name}' (materials[{index}])");
            let (texture, transform) = texture_of(importer, base, &mut textures, info, &role)?;
            shader.texture = Some(texture);
            shader.uv_transform = transform;
        }
        shader.emission = emission(importer, base, &mut textures, &material, report)?;
        shader.transmission = transmission(importer, base, &mut textures, &material, report)?;
        let cutoff = match material.alpha_mode() {
            gltf::material::AlphaMode::Opaque => None,
            gltf::material::AlphaMode::Mask => Some(material.alpha_cutoff().unwrap_or(0.5)),
            gltf::material::AlphaMode::Blend => Some(0.5),
        };
        if let Some(cutoff) = cutoff {
            // The mask tests texture alpha × factor alpha against the cutoff.
            if shader.texture.is_none() {
                let white = Texture::from_srgba8(1, 1, vec![[255; 4]]).expect("1×1 texels");
                shader.texture = Some(Arc::new(white));
            }
            shader.alpha_cutoff = Some(if a > 0.0 { cutoff / a } else { f32::INFINITY });
        }
        shaders.push(shader);
    }
    let mut default = Shader::color(ShaderId(shaders.len() as u32), Vec3::ONE);
    default.double_sided = false;
    shaders.push(default);
    Ok(shaders)
}

/// The material's emissive factor × `KHR_materials_emissive_strength` × emissive
/// texture, or `None` when it emits nothing. A negative or non-finite factor or strength
/// is an error naming the material; an emissive texture on another UV set than the base
/// colour's is left out (Sylva keeps one set per mesh) and counted.
fn emission(
    importer: &Importer,
    base: &Path,
    textures: &mut [Option<Arc<Texture>>],
    material: &gltf::Material,
    report: &mut ImportReport,
) -> Result<Option<Emission>, GltfError> {
    let index = material.index().unwrap_or(0);
    let at = format!("materials[{index}]");
    let factor = Vec3::from(material.emissive_factor());
    if !factor.is_finite() || factor.min_element() < 0.0 {
        return Err(importer.error(
            format!("{at}.emissiveFactor"),
            format!("must be finite and non-negative, not {factor}"),
        ));
    }
    let strength = material.emissive_strength().unwrap_or(1.0);
    if !strength.is_finite() || strength < 0.0 {
        return Err(importer.error(
            format!("{at}.extensions.KHR_materials_emissive_strength.emissiveStrength"),
            format!("must be finite and non-negative, not {strength}"),
        ));
    }
    let radiance = factor * strength;
    if radiance == Vec3::ZERO {
        return Ok(None);
    }
    let mut emission = Emission {
        radiance,
        texture: None,
        uv_transform: None,
    };
    if let Some(info) = &material.emissive_texture() {
        if texture_set(info) == material_uv_set(material) {
            let name = material.name().unwrap_or("");
            let role = format!("emissiveTexture of material '{name}' ({at})");
            let (texture, transform) = texture_of(importer, base, textures, info, &role)?;
            emission.texture = Some(texture);
            emission.uv_transform = transform;
        } else {
            report.textures_left_out += 1;
        }
    }
    Ok(Some(emission))
}

/// Minimal base64 (RFC 4648) for `data:` image URIs.
fn base64_decode(text: &str) -> Option<Vec<u8>> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => Some(c - b'A'),
        b'a'..=b'z' => Some(c - b'a' + 26),
        b'0'..=b'9' => Some(c - b'0' + 52),
        b'+' | b'-' => Some(62),
        b'/' | b'_' => Some(63),
        _ => None,
    };
    let clean: Vec<u8> = text
        .bytes()
        .filter(|&c| c != b'=' && !c.is_ascii_whitespace())
        .collect();
    let mut out = Vec::with_capacity(clean.len() * 3 / 4);
    for chunk in clean.chunks(4) {
        let v: Vec<u8> = chunk.iter().map(|&c| value(c)).collect::<Option<_>>()?;
        let n = v
            .iter()
            .enumerate()
            .fold(0u32, |n, (i, &x)| n | (x as u32) << (18 - 6 * i));
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    Some(out)
}

/// Where an image's bytes are.
enum ImageSource<'a> {
    View(gltf::buffer::View<'a>),
    Uri(&'a str),
}

fn decode_image(
    importer: &Importer,
    image: &gltf::Image,
    base: &Path,
    role: &str,
) -> Result<Texture, GltfError> {
    let at = format!("images[{}] ({role})", image.index());
    // Read the source from the JSON: gltf's `Image::source` unwraps a missing uri, a
    // missing mimeType beside a bufferView, and a bufferView index out of range.
    let raw = &importer.document.as_json().images[image.index()];
    let source = match (&raw.buffer_view, &raw.uri) {
        (Some(view), _) => {
            let view = importer
                .document
                .views()
                .nth(view.value())
                .ok_or_else(|| importer.error(at.clone(), "bufferView index out of range"))?;
            ImageSource::View(view)
        }
        (None, Some(uri)) => ImageSource::Uri(uri.as_str()),
        (None, None) => {
            return Err(importer.error(at, "the image has neither a uri nor a bufferView"));
        }
    };
    let bytes: Vec<u8> = match source {
        ImageSource::View(view) => {
            let data = importer
                .buffers
                .get(view.buffer().index())
                .and_then(|b| b.0.get(view.offset()..view.offset() + view.length()))
                .ok_or_else(|| importer.error(at.clone(), "buffer view out of range"))?;
            data.to_vec()
        }
        ImageSource::Uri(uri) => {
            if let Some(rest) = uri.strip_prefix("data:") {
                let payload = rest.split_once(";base64,").map(|(_, p)| p);
                payload
                    .and_then(base64_decode)
                    .ok_or_else(|| importer.error(at.clone(), "malformed data: URI"))?
            } else {
                let file = base.join(uri);
                std::fs::read(&file).map_err(|e| {
                    importer.error(at.clone(), format!("cannot read '{}': {e}", file.display()))
                })?
            }
        }
    };
    decode_texture(&bytes).map_err(|message| importer.error(at, message))
}

/// Decodes a PNG or JPEG texture (sRGB colour, grey + alpha kept as such), checking its
/// dimensions (edges 1 … `MAX_TEXTURE_EDGE`) before allocating for its pixels.
pub fn decode_texture(bytes: &[u8]) -> Result<Texture, String> {
    let reader = || {
        image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| e.to_string())
    };
    let (width, height) = reader()?
        .into_dimensions()
        .map_err(|e| format!("cannot decode image: {e}"))?;
    if width == 0 || height == 0 || width > MAX_TEXTURE_EDGE || height > MAX_TEXTURE_EDGE {
        return Err(format!(
            "image is {width}×{height}; edges must lie in 1 … {MAX_TEXTURE_EDGE}"
        ));
    }
    let decoded = reader()?
        .decode()
        .map_err(|e| format!("cannot decode image: {e}"))?;
    let texture = match decoded {
        image::DynamicImage::ImageLumaA8(img) => {
            let texels: Vec<[u8; 2]> = img.pixels().map(|p| p.0).collect();
            Texture::from_gray_alpha8(width, height, &texels)
        }
        other => {
            let rgba = other.to_rgba8();
            Texture::from_srgba8(width, height, rgba.pixels().map(|p| p.0).collect())
        }
    };
    texture.map_err(|e| e.to_string())
}

/// Refuses a bufferView whose byteStride is smaller than the accessor's items: gltf's
/// reader would read overlapping items (or, with debug assertions, panic; fuzz finding).
fn check_stride(
    importer: &Importer,
    accessor: &gltf::Accessor,
    location: &str,
) -> Result<(), GltfError> {
    match accessor.view().and_then(|v| v.stride()) {
        Some(stride) if stride < accessor.size() => Err(importer.error(
            location.to_string(),
            format!(
                "bufferView byteStride {stride} is smaller than the {}-byte items",
                accessor.size()
            ),
        )),
        _ => Ok(()),
    }
}

/// Refuses an accessor whose stride, dimensions or component type is not one of the
/// `allowed` layout (`expected` describes it for the error).
fn check_layout(
    importer: &Importer,
    accessor: &gltf::Accessor,
    location: &str,
    allowed: (gltf::accessor::Dimensions, &[gltf::accessor::DataType]),
    expected: &str,
) -> Result<(), GltfError> {
    check_stride(importer, accessor, location)?;
    if accessor.dimensions() != allowed.0 || !allowed.1.contains(&accessor.data_type()) {
        return Err(importer.error(
            location.to_string(),
            format!(
                "expected {expected}, found {:?} of {:?}",
                accessor.dimensions(),
                accessor.data_type()
            ),
        ));
    }
    Ok(())
}

/// Reads an accessor fully, or names it in an error.
fn read_accessor<T: gltf::accessor::Item + Copy>(
    importer: &Importer,
    accessor: gltf::Accessor,
    location: &str,
) -> Result<Vec<T>, GltfError> {
    if accessor.count() == 0 {
        return Ok(Vec::new());
    }
    // Items here are f32 vectors; integer (quantized) data would be misread.
    if accessor.data_type() != gltf::accessor::DataType::F32
        || std::mem::size_of::<T>() != accessor.size()
    {
        return Err(importer.error(
            location.to_string(),
            format!(
                "expected a float accessor of {} bytes per item, found {:?} × {} bytes \
                 (KHR_mesh_quantization is not supported)",
                std::mem::size_of::<T>(),
                accessor.data_type(),
                accessor.size()
            ),
        ));
    }
    check_stride(importer, &accessor, location)?;
    gltf::accessor::Iter::<T>::new(accessor, importer.buffer_data())
        .map(|it| it.collect())
        .ok_or_else(|| {
            importer.error(
                location.to_string(),
                "accessor data lies outside its buffer (truncated file?)",
            )
        })
}

fn mesh(
    importer: &Importer,
    report: &mut ImportReport,
    mesh: &gltf::Mesh,
    default_slot: u32,
) -> Result<GltfMesh, GltfError> {
    let mut out = TriangleMesh::default();
    let mut has_normals = true;
    let mut pieces = Vec::new();
    for primitive in mesh.primitives() {
        let at = format!("meshes[{}].primitives[{}]", mesh.index(), primitive.index());
        let mode = primitive.mode();
        use gltf::mesh::Mode;
        if !matches!(
            mode,
            Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
        ) {
            report.skipped_primitives += 1;
            continue;
        }
        let reader = primitive.reader(importer.buffer_data());
        let Some(position_accessor) = primitive.get(&gltf::Semantic::Positions) else {
            return Err(importer.error(format!("{at}.attributes.POSITION"), "missing"));
        };
        let positions: Vec<[f32; 3]> = read_accessor(
            importer,
            position_accessor,
            &format!("{at}.attributes.POSITION"),
        )?;
        let normals: Option<Vec<[f32; 3]>> = match primitive.get(&gltf::Semantic::Normals) {
            Some(a) => Some(read_accessor(
                importer,
                a,
                &format!("{at}.attributes.NORMAL"),
            )?),
            None => None,
        };
        let material = primitive.material();
        let set = material_uv_set(&material);
        // gltf's reader assumes the layouts the specification allows and misreads (or,
        // with debug assertions, panics on) others: check them first (fuzz finding).
        use gltf::accessor::{DataType, Dimensions};
        if let Some(a) = primitive.get(&gltf::Semantic::TexCoords(set)) {
            check_layout(
                importer,
                &a,
                &format!("{at}.attributes.TEXCOORD_{set}"),
                (
                    Dimensions::Vec2,
                    &[DataType::F32, DataType::U8, DataType::U16],
                ),
                "VEC2 of float, unsigned byte or unsigned short",
            )?;
        }
        if let Some(a) = primitive.indices() {
            check_layout(
                importer,
                &a,
                &format!("{at}.indices"),
                (
                    Dimensions::Scalar,
                    &[DataType::U8, DataType::U16, DataType::U32],
                ),
                "SCALAR unsigned integers",
            )?;
        }
        let uvs: Vec<[f32; 2]> = match reader.read_tex_coords(set) {
            Some(t) => t.into_f32().collect(),
            None if primitive.get(&gltf::Semantic::TexCoords(set)).is_some() => {
                return Err(importer.error(
                    format!("{at}.attributes.TEXCOORD_{set}"),
                    "accessor data lies outside its buffer (truncated file?)",
                ));
            }
            None => vec![[0.0; 2]; positions.len()],
        };
        let n = positions.len();
        if normals.as_ref().is_some_and(|v| v.len() != n) || uvs.len() != n {
            return Err(importer.error(at.clone(), "attribute counts differ from POSITION's"));
        }
        let indices: Vec<u32> = match primitive.indices() {
            Some(a) => {
                if a.count() == 0 {
                    Vec::new()
                } else {
                    reader
                        .read_indices()
                        .map(|r| r.into_u32().collect())
                        .ok_or_else(|| {
                            importer.error(
                                format!("{at}.indices"),
                                "accessor data lies outside its buffer (truncated file?)",
                            )
                        })?
                }
            }
            None => (0..n as u32).collect(),
        };
        if let Some(bad) = indices.iter().find(|&&i| i as usize >= n) {
            return Err(importer.error(
                format!("{at}.indices"),
                format!("index {bad} is out of range for {n} vertices"),
            ));
        }
        let triangles: Vec<[u32; 3]> = match mode {
            Mode::Triangles => indices
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect(),
            Mode::TriangleStrip => (2..indices.len())
                .map(|i| {
                    if i % 2 == 0 {
                        [indices[i - 2], indices[i - 1], indices[i]]
                    } else {
                        [indices[i - 1], indices[i - 2], indices[i]]
                    }
                })
                .collect(),
            _ => (2..indices.len())
                .map(|i| [indices[i - 1], indices[i], indices[0]])
                .collect(),
        };
        let finite: Vec<bool> = positions
            .iter()
            .map(|p| p.iter().all(|c| c.is_finite()))
            .collect();
        report.non_finite_vertices += finite.iter().filter(|f| !**f).count();
        let slot = material.index().map_or(default_slot, |i| i as u32);
        has_normals &= normals.is_some();
        pieces.push((positions, normals, uvs, triangles, finite, slot));
    }
    for (positions, normals, uvs, triangles, finite, slot) in pieces {
        let kept: Vec<[u32; 3]> = triangles
            .into_iter()
            .filter(|t| {
                let ok = t.iter().all(|&i| finite[i as usize]);
                report.dropped_triangles += usize::from(!ok);
                ok
            })
            .collect();
        if has_normals {
            let base = out.positions.len() as u32;
            out.positions
                .extend(positions.iter().map(|&p| Vec3::from(p)));
            let normals = normals.expect("has_normals");
            out.normals
                .extend(normals.iter().map(|&n| Vec3::from(n).normalize_or(Vec3::Y)));
            out.uvs.extend(uvs.iter().map(|&t| Vec2::from(t)));
            out.indices.extend(kept.iter().map(|t| t.map(|i| i + base)));
        } else {
            // Flat normals (glTF's rule for primitives without NORMAL): one vertex per
            // corner, the face normal on all three; a mesh mixing both gets flat normals
            // everywhere.
            for t in &kept {
                let p = t.map(|i| Vec3::from(positions[i as usize]));
                let normal = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or(Vec3::Y);
                let base = out.positions.len() as u32;
                for (k, &i) in t.iter().enumerate() {
                    out.positions.push(p[k]);
                    out.normals.push(normal);
                    out.uvs.push(Vec2::from(uvs[i as usize]));
                }
                out.indices.push([base, base + 1, base + 2]);
            }
        }
        out.shaders.extend(std::iter::repeat_n(slot, kept.len()));
    }
    Ok(GltfMesh {
        name: mesh
            .name()
            .map_or_else(|| format!("mesh {}", mesh.index()), str::to_string),
        mesh: out,
    })
}

fn affine(matrix: [[f32; 4]; 4]) -> Affine3A {
    Affine3A::from_mat4(Mat4::from_cols_array_2d(&matrix))
}

/// Per-instance transforms of `EXT_mesh_gpu_instancing`, or `None` without it.
fn gpu_instances(
    importer: &Importer,
    node: &gltf::Node,
) -> Result<Option<Vec<Affine3A>>, GltfError> {
    let Some(ext) = node.extension_value("EXT_mesh_gpu_instancing") else {
        return Ok(None);
    };
    let at = format!("nodes[{}].extensions.EXT_mesh_gpu_instancing", node.index());
    let attributes = ext
        .get("attributes")
        .and_then(|a| a.as_object())
        .ok_or_else(|| importer.error(at.clone(), "missing 'attributes'"))?;
    let accessor = |name: &str| -> Result<Option<gltf::Accessor>, GltfError> {
        match attributes.get(name) {
            None => Ok(None),
            Some(v) => {
                let index = v.as_u64().ok_or_else(|| {
                    importer.error(format!("{at}.attributes.{name}"), "not an accessor index")
                })?;
                importer
                    .document
                    .accessors()
                    .nth(index as usize)
                    .map(Some)
                    .ok_or_else(|| {
                        importer.error(
                            format!("{at}.attributes.{name}"),
                            format!("accessor {index} does not exist"),
                        )
                    })
            }
        }
    };
    // read_accessor refuses non-float data, which the extension allows only quantized.
    let translations: Option<Vec<[f32; 3]>> = accessor("TRANSLATION")?
        .map(|a| read_accessor(importer, a, &format!("{at}.attributes.TRANSLATION")))
        .transpose()?;
    let rotations: Option<Vec<[f32; 4]>> = accessor("ROTATION")?
        .map(|a| read_accessor(importer, a, &format!("{at}.attributes.ROTATION")))
        .transpose()?;
    let scales: Option<Vec<[f32; 3]>> = accessor("SCALE")?
        .map(|a| read_accessor(importer, a, &format!("{at}.attributes.SCALE")))
        .transpose()?;
    let counts: Vec<usize> = [
        translations.as_ref().map(Vec::len),
        rotations.as_ref().map(Vec::len),
        scales.as_ref().map(Vec::len),
    ]
    .into_iter()
    .flatten()
    .collect();
    let count = counts.first().copied().unwrap_or(0);
    if counts.iter().any(|&c| c != count) {
        return Err(importer.error(at, "TRANSLATION, ROTATION and SCALE counts differ"));
    }
    Ok(Some(
        (0..count)
            .map(|i| {
                let t = translations
                    .as_ref()
                    .map_or(Vec3::ZERO, |v| Vec3::from(v[i]));
                let r = rotations
                    .as_ref()
                    .map_or(Quat::IDENTITY, |v| Quat::from_array(v[i]).normalize());
                let s = scales.as_ref().map_or(Vec3::ONE, |v| Vec3::from(v[i]));
                Affine3A::from_scale_rotation_translation(s, r, t)
            })
            .collect(),
    ))
}

type NodeOutput = (Vec<GltfInstance>, Vec<GltfCamera>);

fn nodes(importer: &Importer, report: &mut ImportReport) -> Result<NodeOutput, GltfError> {
    let roots: Vec<gltf::Node> = match importer
        .document
        .default_scene()
        .or_else(|| importer.document.scenes().next())
    {
        Some(scene) => scene.nodes().collect(),
        None => importer.document.nodes().collect(),
    };
    let mut instances = Vec::new();
    let mut cameras = Vec::new();
    // Depth-first with an explicit stack; validation guarantees the hierarchy is a forest.
    let mut stack: Vec<(gltf::Node, Affine3A, usize)> = roots
        .into_iter()
        .rev()
        .map(|n| (n, Affine3A::IDENTITY, 0))
        .collect();
    while let Some((node, parent, depth)) = stack.pop() {
        if depth > 1024 {
            return Err(importer.error(format!("nodes[{}]", node.index()), "hierarchy too deep"));
        }
        let world = parent * affine(node.transform().matrix());
        let name = node
            .name()
            .map_or_else(|| format!("nodes[{}]", node.index()), str::to_string);
        if let Some(mesh) = node.mesh() {
            let locals =
                gpu_instances(importer, &node)?.unwrap_or_else(|| vec![Affine3A::IDENTITY]);
            for local in locals {
                let transform = world * local;
                let det = transform.matrix3.determinant();
                if !det.is_finite() || det.abs() < 1e-30 || !transform.translation.is_finite() {
                    report.singular_instances += 1;
                    continue;
                }
                instances.push(GltfInstance {
                    mesh: mesh.index(),
                    transform,
                    node: name.clone(),
                    node_index: node.index(),
                    local,
                });
            }
        }
        if let Some(camera) = node.camera() {
            match camera.projection() {
                gltf::camera::Projection::Perspective(p) => cameras.push(GltfCamera {
                    name: camera
                        .name()
                        .map_or_else(|| format!("cameras[{}]", camera.index()), str::to_string),
                    yfov: p.yfov(),
                    aspect_ratio: p.aspect_ratio(),
                    transform: world,
                }),
                gltf::camera::Projection::Orthographic(_) => report.orthographic_cameras += 1,
            }
        }
        for child in node.children().collect::<Vec<_>>().into_iter().rev() {
            stack.push((child, world, depth + 1));
        }
    }
    Ok((instances, cameras))
}

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
fn framing_view(bounds: Aabb) -> (Camera, Transform) {
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

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

mod animation;
mod images;
mod material;
mod mesh;
mod nodes;
mod scene;

use animation::animation;
pub use images::decode_texture;
use material::materials;
use mesh::mesh;
use nodes::nodes;
pub use scene::CameraChoice;

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

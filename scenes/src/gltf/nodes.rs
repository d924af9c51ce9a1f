//! The node tree: world transforms, instances of meshes (`EXT_mesh_gpu_instancing`
//! included) and cameras.

use super::mesh::read_accessor;
use super::*;

pub(super) fn affine(matrix: [[f32; 4]; 4]) -> Affine3A {
    Affine3A::from_mat4(Mat4::from_cols_array_2d(&matrix))
}

/// Per-instance transforms of `EXT_mesh_gpu_instancing`, or `None` without it.
pub(super) fn gpu_instances(
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

pub(super) type NodeOutput = (Vec<GltfInstance>, Vec<GltfCamera>);

pub(super) fn nodes(
    importer: &Importer,
    report: &mut ImportReport,
) -> Result<NodeOutput, GltfError> {
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

//! glTF primitives as triangle meshes: accessors read with their layout checked,
//! indices, normals, UVs and shaders per triangle, bad vertices dropped and counted.

use super::material::material_uv_set;
use super::*;

/// Refuses a bufferView whose byteStride is smaller than the accessor's items: gltf's
/// reader would read overlapping items (or, with debug assertions, panic; fuzz finding).
pub(super) fn check_stride(
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
pub(super) fn check_layout(
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
pub(super) fn read_accessor<T: gltf::accessor::Item + Copy>(
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

pub(super) fn mesh(
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

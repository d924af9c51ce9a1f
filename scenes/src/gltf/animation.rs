//! glTF animations: node translation, rotation and scale channels with their samplers,
//! bound to the instances they move.

use super::*;

/// The node hierarchy with its rest poses and every animation's TRS channels, checked:
/// key times finite and not decreasing, one output per key (three for CUBICSPLINE).
pub(super) fn animation(
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

//! glTF materials as shaders: base colour and its texture (wrap modes, UV set,
//! `KHR_texture_transform`), alpha modes, emission and diffuse transmission.

use super::images::decode_image;
use super::*;

pub(super) fn wrap_mode(mode: gltf::texture::WrappingMode) -> WrapMode {
    match mode {
        gltf::texture::WrappingMode::ClampToEdge => WrapMode::ClampToEdge,
        gltf::texture::WrappingMode::MirroredRepeat => WrapMode::MirroredRepeat,
        gltf::texture::WrappingMode::Repeat => WrapMode::Repeat,
    }
}

/// The texture coordinate set a texture reference reads (its transform may override it).
pub(super) fn texture_set(info: &gltf::texture::Info) -> u32 {
    info.texture_transform()
        .and_then(|t| t.tex_coord())
        .unwrap_or(info.tex_coord())
}

/// The UV set a material's meshes keep: its base colour texture's, else its emissive
/// texture's, else 0. Sylva keeps one set per mesh.
pub(super) fn material_uv_set(material: &gltf::Material) -> u32 {
    let base = material.pbr_metallic_roughness().base_color_texture();
    base.or_else(|| material.emissive_texture())
        .map_or(0, |info| texture_set(&info))
}

/// A texture reference decoded once per image, with its sampler's wrap modes and its
/// `KHR_texture_transform`.
pub(super) fn texture_of(
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
pub(super) fn decoded(
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
pub(super) fn raw_texture_ref<'a>(
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
pub(super) fn transmission(
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
pub(super) fn materials(
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
pub(super) fn emission(
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

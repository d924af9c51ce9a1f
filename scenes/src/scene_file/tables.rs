//! One function a table: each checks its values' ranges and turns the table into the
//! ecosystem's specification, with errors that name the file, line, column and key.

use super::*;

/// The `[terrain]` table over the preset's terrain.
pub(super) fn terrain(
    cx: &Context,
    t: &TerrainDoc,
    p: &mut TerrainParams,
) -> Result<(), SceneFileError> {
    if let Some(v) = &t.size {
        p.size = cx.check(v, "terrain.size", 1.0, 1e5)?;
    }
    if let Some(v) = &t.cells {
        p.cells = cx.check(v, "terrain.cells", 1, 2048)?;
    }
    if let Some(v) = &t.amplitude {
        p.amplitude = cx.check(v, "terrain.amplitude", 0.0, 1e4)?;
    }
    if let Some(v) = &t.wavelength {
        p.wavelength = cx.check(v, "terrain.wavelength", 0.01, 1e6)?;
    }
    if let Some(v) = &t.octaves {
        p.octaves = cx.check(v, "terrain.octaves", 1, 16)?;
    }
    if let Some(v) = &t.noise {
        p.ridged = match v.get_ref().as_str() {
            "fbm" => false,
            "ridged" => true,
            other => {
                return Err(cx.error(
                    Some(v.span()),
                    "terrain.noise",
                    format!("unknown noise '{other}' (expected fbm or ridged)"),
                ));
            }
        };
    }
    Ok(())
}

/// The `[sun]` table.
pub(super) fn sun(cx: &Context, s: &SunDoc) -> Result<SunSpec, SceneFileError> {
    Ok(SunSpec {
        elevation: cx.check(&s.elevation, "sun.elevation", -90.0, 90.0)?,
        azimuth: cx.check(&s.azimuth, "sun.azimuth", -360.0, 360.0)?,
        irradiance: match &s.irradiance {
            Some(v) => cx.color(v, "sun.irradiance", 1e6)?,
            None => Vec3::new(3.2, 3.0, 2.7),
        },
    })
}

/// The `[wind]` table (defaults: a calm breeze's gusts, from the east).
pub(super) fn wind(cx: &Context, w: &WindDoc) -> Result<sylva_engine::sway::Wind, SceneFileError> {
    let calm = sylva_engine::sway::Wind::default();
    let direction = match &w.direction {
        Some(d) => cx.check(d, "wind.direction", -360.0, 360.0)?.to_radians(),
        None => 90f32.to_radians(),
    };
    let optional = |value: &Option<Spanned<f32>>, key, low, high, default| match value {
        Some(v) => cx.check(v, key, low, high),
        None => Ok(default),
    };
    Ok(sylva_engine::sway::Wind {
        direction: glam::Vec2::new(direction.sin(), direction.cos()),
        speed: cx.check(&w.speed, "wind.speed", 0.0, 60.0)?,
        gustiness: optional(&w.gustiness, "wind.gustiness", 0.0, 2.0, calm.gustiness)?,
        gust_frequency: optional(
            &w.gust_frequency,
            "wind.gust_frequency",
            0.001,
            20.0,
            calm.gust_frequency,
        )?,
        gust_wavelength: optional(
            &w.gust_wavelength,
            "wind.gust_wavelength",
            0.1,
            10_000.0,
            calm.gust_wavelength,
        )?,
        strength: 1.0,
        turbulence: optional(&w.turbulence, "wind.turbulence", 0.0, 2.0, 0.0)?,
        seed: w.seed.unwrap_or(0),
    })
}

/// The `[sky]` table: a Preetham sky by its turbidity, or a gradient by its colours.
pub(super) fn sky(cx: &Context, s: &SkyDoc) -> Result<SkySpec, SceneFileError> {
    Ok(match (&s.turbidity, &s.zenith, &s.horizon, &s.ground) {
        (Some(t), None, None, None) => SkySpec::Preetham {
            turbidity: cx.check(t, "sky.turbidity", 1.7, 10.0)?,
        },
        (None, Some(zenith), Some(horizon), Some(ground)) => SkySpec::Gradient(SkyLight {
            zenith: cx.color(zenith, "sky.zenith", 1e6)?,
            horizon: cx.color(horizon, "sky.horizon", 1e6)?,
            ground: cx.color(ground, "sky.ground", 1e6)?,
        }),
        _ => {
            return Err(cx.error(
                None,
                "sky",
                "give either `turbidity` (the Preetham sky) or all of `zenith`, `horizon` and `ground` (a gradient)".into(),
            ));
        }
    })
}

/// The `[camera]` table and its `[[camera.path]]` keys: the still camera (its own eye
/// and target, or the path's first key) and the path, if any.
pub(super) fn camera(
    cx: &Context,
    c: &CameraDoc,
) -> Result<(CameraSpec, Option<CameraPathSpec>), SceneFileError> {
    let finite = |v: [f32; 2], key: &str| {
        if v.iter().all(|x| x.is_finite()) {
            Ok(Vec2::from(v))
        } else {
            Err(cx.error(None, key, format!("{v:?} is not finite")))
        }
    };
    let height = |v: &Option<Spanned<f32>>, key: &str, default: f32| match v {
        Some(v) => cx.check(v, key, -1e4, 1e5),
        None => Ok(default),
    };
    let fov = |v: &Option<Spanned<f32>>, key: &str, default: f32| match v {
        Some(v) => cx.check(v, key, 1.0, 170.0),
        None => Ok(default),
    };
    let eye_height = height(&c.eye_height, "camera.eye_height", 1.7)?;
    let target_height = height(&c.target_height, "camera.target_height", 1.7)?;
    let camera_fov = fov(&c.fov, "camera.fov", 55.0)?;
    let path = match &c.path {
        Some(keys) => Some(camera_path(
            cx,
            keys,
            &c.path_interpolation,
            (eye_height, target_height, camera_fov),
        )?),
        None => {
            if let Some(i) = &c.path_interpolation {
                return Err(cx.error(
                    Some(i.span()),
                    "camera.path_interpolation",
                    "there is no [[camera.path]] to interpolate".into(),
                ));
            }
            None
        }
    };
    // Without its own eye and target, the still camera is the path's first key.
    let first_target = path.as_ref().and_then(|p| match p.keys[0].aim {
        CameraAim::Target(target, height) => Some((p.keys[0], target, height)),
        CameraAim::Rotation(_) => None,
    });
    let still = match (c.eye, c.target, first_target) {
        (Some(eye), Some(target), _) => CameraSpec {
            eye: finite(eye, "camera.eye")?,
            eye_height,
            target: finite(target, "camera.target")?,
            target_height,
            fov: camera_fov,
        },
        (None, None, Some((key, target, height))) => CameraSpec {
            eye: key.eye,
            eye_height: key.eye_height,
            target,
            target_height: height,
            fov: key.fov,
        },
        _ => {
            return Err(cx.error(
                None,
                "camera",
                "give `eye` and `target`, or a [[camera.path]] whose first key has a `target`"
                    .into(),
            ));
        }
    };
    Ok((still, path))
}

/// The `[[plant]]` tables: explicit plants, each with a finite transform, a unit rotation
/// and a layer among the scene's `layers`.
pub(super) fn plants(
    cx: &Context,
    plants: &[Spanned<PlantDoc>],
    layers: usize,
) -> Result<Vec<PlacedPlant>, SceneFileError> {
    let mut list = Vec::with_capacity(plants.len());
    for (i, plant) in plants.iter().enumerate() {
        let p = plant.get_ref();
        let key = format!("plant[{i}]");
        let finite = p
            .translation
            .iter()
            .chain(&p.rotation)
            .chain(&p.scale)
            .all(|v| v.is_finite());
        let rotation = glam::Quat::from_array(p.rotation);
        if !finite || (rotation.length() - 1.0).abs() > 1e-3 || p.scale.iter().any(|&v| v <= 0.0) {
            return Err(cx.error(
                Some(plant.span()),
                &key,
                "needs finite numbers, a unit rotation quaternion [x, y, z, w] and a positive scale".into(),
            ));
        }
        if p.layer as usize >= layers {
            return Err(cx.error(
                Some(plant.span()),
                &key,
                format!("layer {} does not exist ({} layers)", p.layer, layers),
            ));
        }
        list.push(PlacedPlant {
            species: p.species.clone(),
            layer: p.layer,
            transform: Transform {
                translation: Vec3::from(p.translation),
                rotation,
                scale: Vec3::from(p.scale),
            },
        });
    }
    Ok(list)
}

/// The `[[camera.path]]` key frames, checked by key: times increasing, a `target` or a
/// `rotation` each; heights and field of view default to the camera's.
pub(super) fn camera_path(
    cx: &Context,
    keys: &[Spanned<CameraKeyDoc>],
    interpolation: &Option<Spanned<String>>,
    (eye_height, target_height, fov): (f32, f32, f32),
) -> Result<CameraPathSpec, SceneFileError> {
    let interpolation = match interpolation {
        None => PathInterpolation::CatmullRom,
        Some(name) => match name.get_ref().as_str() {
            "catmull_rom" => PathInterpolation::CatmullRom,
            "linear" => PathInterpolation::Linear,
            other => {
                return Err(cx.error(
                    Some(name.span()),
                    "camera.path_interpolation",
                    format!("'{other}' is not catmull_rom or linear"),
                ));
            }
        },
    };
    if keys.is_empty() {
        return Err(cx.error(None, "camera.path", "needs at least one key frame".into()));
    }
    let mut out: Vec<CameraKeySpec> = Vec::with_capacity(keys.len());
    for (i, spanned) in keys.iter().enumerate() {
        let k = spanned.get_ref();
        let key = |name: &str| format!("camera.path[{i}].{name}");
        let time = cx.check(&k.time, &key("time"), 0.0, 1e6)?;
        if let Some(previous) = out.last()
            && time <= previous.time
        {
            return Err(cx.error(
                Some(k.time.span()),
                &key("time"),
                format!(
                    "{time} does not come after the key before it ({})",
                    previous.time
                ),
            ));
        }
        let finite2 = |v: [f32; 2]| v.iter().all(|x| x.is_finite());
        if !finite2(k.eye) {
            return Err(cx.error(
                Some(spanned.span()),
                &key("eye"),
                format!("{:?} is not finite", k.eye),
            ));
        }
        let aim = match (k.target, k.rotation) {
            (Some(target), None) if finite2(target) => {
                let height = match &k.target_height {
                    Some(v) => cx.check(v, &key("target_height"), -1e4, 1e5)?,
                    None => target_height,
                };
                CameraAim::Target(Vec2::from(target), height)
            }
            (None, Some(r)) => {
                let rotation = glam::Quat::from_array(r);
                if !rotation.is_finite() || (rotation.length() - 1.0).abs() > 1e-3 {
                    return Err(cx.error(
                        Some(spanned.span()),
                        &key("rotation"),
                        format!("{r:?} is not a unit quaternion [x, y, z, w]"),
                    ));
                }
                CameraAim::Rotation(rotation.normalize())
            }
            _ => {
                return Err(cx.error(
                    Some(spanned.span()),
                    &format!("camera.path[{i}]"),
                    "give either a finite `target` or a `rotation`".into(),
                ));
            }
        };
        out.push(CameraKeySpec {
            time,
            eye: Vec2::from(k.eye),
            eye_height: match &k.eye_height {
                Some(v) => cx.check(v, &key("eye_height"), -1e4, 1e5)?,
                None => eye_height,
            },
            aim,
            fov: match &k.fov {
                Some(v) => cx.check(v, &key("fov"), 1.0, 170.0)?,
                None => fov,
            },
        });
    }
    Ok(CameraPathSpec {
        keys: out,
        interpolation,
    })
}

pub(super) fn layer(cx: &Context, doc: &LayerDoc, i: usize) -> Result<LayerSpec, SceneFileError> {
    let key = |k: &str| format!("layer[{i}].{k}");
    let count = cx.check(&doc.count, &key("count"), 0, 10_000_000)?;
    let scale = match &doc.scale {
        Some(s) => {
            let [lo, hi] = *s.get_ref();
            if !(lo > 0.0 && hi >= lo && hi < 1e4) {
                return Err(cx.error(
                    Some(s.span()),
                    &key("scale"),
                    format!("[{lo}, {hi}] must satisfy 0 < low ≤ high"),
                ));
            }
            (lo, hi)
        }
        None => (0.8, 1.2),
    };
    let region = match &doc.region {
        Some(r) => {
            let [x0, z0, x1, z1] = *r.get_ref();
            if !(x0 < x1 && z0 < z1) || [x0, z0, x1, z1].iter().any(|v| !v.is_finite()) {
                return Err(cx.error(
                    Some(r.span()),
                    &key("region"),
                    "expected [x0, z0, x1, z1] with x0 < x1 and z0 < z1".into(),
                ));
            }
            Some([x0, z0, x1, z1])
        }
        None => None,
    };
    if doc.species.get_ref().is_empty() && count > 0 {
        return Err(cx.error(
            Some(doc.species.span()),
            &key("species"),
            "a layer with plants needs at least one species".into(),
        ));
    }
    let species = doc
        .species
        .get_ref()
        .iter()
        .enumerate()
        .map(|(j, s)| species(cx, s, &format!("layer[{i}].species[{j}]")))
        .collect::<Result<Vec<_>, _>>()?
        .concat();
    Ok(LayerSpec {
        name: doc.name.clone(),
        species,
        count,
        scale,
        min_spacing: doc
            .min_spacing
            .as_ref()
            .map(|v| cx.check(v, &key("min_spacing"), 0.0, 1e4))
            .transpose()?,
        clustering: doc
            .clustering
            .as_ref()
            .map(|v| cx.check(v, &key("clustering"), 0.0, 1.0))
            .transpose()?
            .unwrap_or(0.0),
        region,
        sway: sway(cx, &doc.sway, &key("sway"))?,
    })
}

/// A `sway` table's factors, each in 0.01 … 100.
pub(super) fn sway(
    cx: &Context,
    doc: &Option<SwayDoc>,
    key: &str,
) -> Result<SwaySpec, SceneFileError> {
    let Some(doc) = doc else {
        return Ok(SwaySpec::default());
    };
    let factor = |value: &Option<Spanned<f32>>, name: &str| {
        value
            .as_ref()
            .map(|v| cx.check(v, &format!("{key}.{name}"), 0.01, 100.0))
            .transpose()
    };
    Ok(SwaySpec {
        stiffness: factor(&doc.stiffness, "stiffness")?,
        damping: factor(&doc.damping, "damping")?,
        inertia: factor(&doc.inertia, "inertia")?,
    })
}

/// A `[[layer.species]]` table: one species, or with `variants = N` the N generated
/// species of a family (heights drawn from the `height` range, triangle counts spread
/// ±25 % about `triangles`, each its own seed; named "NAME 1" … "NAME N").
pub(super) fn species(
    cx: &Context,
    doc: &SpeciesDoc,
    key: &str,
) -> Result<Vec<SpeciesSpec>, SceneFileError> {
    let k = |f: &str| format!("{key}.{f}");
    let sway = sway(cx, &doc.sway, &k("sway"))?;
    let weight = doc
        .weight
        .as_ref()
        .map(|v| cx.check(v, &k("weight"), 0.0, 1e6))
        .transpose()?
        .unwrap_or(1.0);
    let name = doc.name.get_ref().clone();
    if let Some(file) = &doc.gltf {
        if let Some(kind) = &doc.kind {
            return Err(cx.error(
                Some(kind.span()),
                &k("kind"),
                "a species comes either from `gltf` or from `kind`, not both".into(),
            ));
        }
        if let Some(variants) = &doc.variants {
            return Err(cx.error(
                Some(variants.span()),
                &k("variants"),
                "variants are generated: a glTF species has none".into(),
            ));
        }
        let base = cx.path.parent().unwrap_or(Path::new("."));
        return Ok(vec![SpeciesSpec {
            name,
            source: SpeciesSource::Gltf {
                path: base.join(file.get_ref()),
            },
            weight,
            sway,
        }]);
    }
    let Some(kind_name) = &doc.kind else {
        return Err(cx.error(
            Some(doc.name.span()),
            key,
            "a species needs `kind` (procedural) or `gltf` (a model file)".into(),
        ));
    };
    let kind = PlantKind::from_name(kind_name.get_ref()).ok_or_else(|| {
        cx.error(
            Some(kind_name.span()),
            &k("kind"),
            format!(
                "unknown kind '{}' (expected {})",
                kind_name.get_ref(),
                PlantKind::ALL.map(PlantKind::name).join(", ")
            ),
        )
    })?;
    let leaf_shape = doc
        .leaf
        .as_ref()
        .map(|l| {
            LeafShape::from_name(l.get_ref()).ok_or_else(|| {
                cx.error(
                    Some(l.span()),
                    &k("leaf"),
                    format!(
                        "unknown leaf shape '{}' (expected {})",
                        l.get_ref(),
                        LeafShape::ALL.map(LeafShape::name).join(", ")
                    ),
                )
            })
        })
        .transpose()?;
    let leaf_color = doc
        .leaf_color
        .as_ref()
        .map(|c| {
            cx.color(c, &k("leaf_color"), 1.0)
                .map(|c| c.map(srgb_to_linear))
        })
        .transpose()?;
    let triangles = doc
        .triangles
        .as_ref()
        .map(|v| cx.check(v, &k("triangles"), 16, 2_000_000))
        .transpose()?
        .unwrap_or(2000);
    let seed = doc.seed.unwrap_or_else(|| {
        // Stable per name, so reordering species does not change them.
        doc.name
            .get_ref()
            .bytes()
            .fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
                (h ^ b as u64).wrapping_mul(0x1000_0000_01b3)
            })
    });
    let height = |h: f32, span| cx.check(&Spanned::new(span, h), &k("height"), 0.01, 500.0);
    let specs = match (&doc.variants, &doc.height) {
        (Some(variants), Some(range)) => {
            let n = cx.check(variants, &k("variants"), 1, 1000)?;
            let HeightDoc::Range([low, high]) = *range.get_ref() else {
                return Err(cx.error(
                    Some(range.span()),
                    &k("height"),
                    "variants draw their heights from a range: give height = [low, high]".into(),
                ));
            };
            let (low, high) = (height(low, range.span())?, height(high, range.span())?);
            if low > high {
                return Err(cx.error(
                    Some(range.span()),
                    &k("height"),
                    format!("[{low}, {high}] must satisfy low ≤ high"),
                ));
            }
            crate::ecosystem::procedural(&name, kind, n, (low, high), triangles, seed)
        }
        (Some(variants), None) => {
            return Err(cx.error(
                Some(variants.span()),
                &k("variants"),
                "variants draw their heights from a range: give height = [low, high]".into(),
            ));
        }
        (None, height_doc) => {
            let height = match height_doc {
                None => kind.typical_height(),
                Some(h) => match *h.get_ref() {
                    HeightDoc::One(v) => height(v, h.span())?,
                    HeightDoc::Range(_) => {
                        return Err(cx.error(
                            Some(h.span()),
                            &k("height"),
                            "a height range is for a family of species: give `variants` too".into(),
                        ));
                    }
                },
            };
            vec![SpeciesSpec {
                name,
                source: SpeciesSource::Procedural {
                    kind,
                    height,
                    triangles,
                    leaf_shape: None,
                    leaf_color: None,
                    seed,
                },
                weight: 1.0,
                sway: SwaySpec::default(),
            }]
        }
    };
    // The table's leaf, colour, weight and sway hold for every variant.
    Ok(specs
        .into_iter()
        .map(|mut spec| {
            if let SpeciesSource::Procedural {
                leaf_shape: shape,
                leaf_color: color,
                ..
            } = &mut spec.source
            {
                *shape = leaf_shape;
                *color = leaf_color;
            }
            SpeciesSpec {
                weight,
                sway,
                ..spec
            }
        })
        .collect())
}

//! Scene files parsed against what they say, and every kind of bad value an error
//! naming its place.

use super::*;

fn parse(text: &str) -> Result<SceneFile, SceneFileError> {
    SceneFile::parse(text, Path::new("scenes/my.toml"))
}

#[test]
fn a_wind_is_read_with_its_defaults() {
    let file = parse("preset = \"meadow\"\n[wind]\nspeed = 8\ndirection = 0\n").unwrap();
    let wind = file.spec.wind.expect("a wind");
    assert_eq!(wind.speed, 8.0);
    assert!(
        (wind.direction - glam::Vec2::Y).length() < 1e-6,
        "toward +Z"
    );
    let calm = sylva_engine::sway::Wind::default();
    assert_eq!(
        (wind.gustiness, wind.gust_frequency, wind.gust_wavelength),
        (calm.gustiness, calm.gust_frequency, calm.gust_wavelength)
    );
    assert_eq!(parse("preset = \"meadow\"\n").unwrap().spec.wind, None);
    let turbulent = parse("[wind]\nspeed = 8\nturbulence = 0.4\nseed = 5\n").unwrap();
    let wind = turbulent.spec.wind.unwrap();
    assert_eq!((wind.turbulence, wind.seed), (0.4, 5));
    let error = parse("[wind]\nspeed = 8\nturbulence = 3\n")
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("wind.turbulence: 3 is out of range"),
        "{error}"
    );
}

#[test]
fn a_preset_with_overrides() {
    let file = parse("preset = \"forest\"\nseed = 9\n[terrain]\ncells = 50\nnoise = \"ridged\"\n")
        .unwrap();
    assert_eq!(file.seed, Some(9));
    assert_eq!(file.spec.terrain.cells, 50);
    assert!(file.spec.terrain.ridged);
    assert_eq!(file.spec.layers, preset("forest").unwrap().layers);
    assert_eq!(file.spec.name, "my");
}

#[test]
fn layers_species_and_relative_gltf_paths() {
    let file = parse(
        r#"

[[layer]]
name = "grass"
count = 40
clustering = 0.5
region = [-5, -5, 5, 5]
[[layer.species]]
name = "g"
kind = "grass"
height = 0.4
triangles = 300
leaf = "blades"
leaf_color = [1.0, 0.5, 0.0]
[[layer.species]]
name = "t"
gltf = "models/tree.glb"
weight = 0.5
[camera]
eye = [0, 8]
target = [0, 0]
"#,
    )
    .unwrap();
    let layer = &file.spec.layers[0];
    assert_eq!((layer.count, layer.clustering), (40, 0.5));
    assert_eq!(layer.region, Some([-5.0, -5.0, 5.0, 5.0]));
    match &layer.species[0].source {
        SpeciesSource::Procedural {
            kind, leaf_color, ..
        } => {
            assert_eq!(*kind, PlantKind::Grass);
            assert_eq!(*leaf_color, Some(Vec3::new(1.0, srgb_to_linear(0.5), 0.0)));
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(
        layer.species[1].source,
        SpeciesSource::Gltf {
            path: PathBuf::from("scenes/models/tree.glb")
        }
    );
    assert_eq!(file.spec.camera.eye, Vec2::new(0.0, 8.0));
}

#[test]
fn a_camera_path_is_read_with_the_cameras_defaults_and_bad_keys_are_refused() {
    let file = parse(
        "preset = \"meadow\"\n[camera]\neye = [0, 10]\ntarget = [0, 0]\neye_height = 3\nfov = 40\npath_interpolation = \"linear\"\n\n[[camera.path]]\ntime = 0\neye = [0, 10]\ntarget = [0, 0]\n\n[[camera.path]]\ntime = 2.5\neye = [5, 5]\nrotation = [0, 0.38268343, 0, 0.9238795]\nfov = 60\n",
    )
    .unwrap();
    let path = file.spec.camera_path.expect("a path");
    assert_eq!(path.interpolation, PathInterpolation::Linear);
    assert_eq!(path.keys.len(), 2);
    assert_eq!(path.keys[0].eye_height, 3.0, "the camera's eye height");
    assert_eq!(path.keys[0].fov, 40.0, "the camera's field of view");
    assert_eq!(path.keys[0].aim, CameraAim::Target(Vec2::ZERO, 1.7));
    assert_eq!(path.keys[1].fov, 60.0);
    assert!(matches!(path.keys[1].aim, CameraAim::Rotation(_)));

    // Without eye and target, the still camera is the first key.
    let only_path =
        parse("preset = \"meadow\"\n[[camera.path]]\ntime = 0\neye = [3, 4]\ntarget = [1, 1]\n")
            .unwrap();
    assert_eq!(only_path.spec.camera.eye, Vec2::new(3.0, 4.0));
    assert_eq!(only_path.spec.camera.target, Vec2::new(1.0, 1.0));
    assert_eq!(
        only_path.spec.camera_path.unwrap().interpolation,
        PathInterpolation::CatmullRom
    );

    let key =
        |time: &str, aim: &str| format!("[[camera.path]]\ntime = {time}\neye = [0, 1]\n{aim}\n");
    for (text, says) in [
        (
            format!(
                "{}{}",
                key("1", "target = [0, 0]"),
                key("1", "target = [1, 0]")
            ),
            "my.toml:6:8: camera.path[1].time: 1 does not come after",
        ),
        (
            key("0", ""),
            "camera.path[0]: give either a finite `target` or a `rotation`",
        ),
        (
            key("0", "target = [0, 0]\nrotation = [0, 0, 0, 1]"),
            "camera.path[0]: give either",
        ),
        (
            key("0", "rotation = [0, 0, 0, 2]"),
            "camera.path[0].rotation",
        ),
        (
            key("-1", "target = [0, 0]"),
            "camera.path[0].time: -1 is out of range",
        ),
        (
            format!(
                "[camera]\npath_interpolation = \"cubic\"\n{}",
                key("0", "target = [0, 0]")
            ),
            "camera.path_interpolation: 'cubic' is not catmull_rom or linear",
        ),
        (
            key("0", "rotation = [0, 0, 0, 1]"),
            "camera: give `eye` and `target`",
        ),
    ] {
        let error = parse(&text).unwrap_err().to_string();
        assert!(error.contains(says), "{text}\n→ {error}");
    }
}

#[test]
fn sway_factors_are_read_per_layer_and_species_and_checked_by_key() {
    let layer = "[[layer]]\nname = \"a\"\ncount = 3\nsway = { stiffness = 2.5 }\n[[layer.species]]\nname = \"g\"\nkind = \"grass\"\n";
    let file = parse(&format!("{layer}sway = {{ inertia = 0.5 }}\n")).unwrap();
    let spec = &file.spec.layers[0];
    assert_eq!(spec.sway.stiffness, Some(2.5));
    assert_eq!(spec.species[0].sway.inertia, Some(0.5));
    let factors = spec.species[0].sway.over(spec.sway);
    assert_eq!(
        (factors.stiffness, factors.damping, factors.inertia),
        (2.5, 1.0, 0.5)
    );
    for (bad, says) in [
        (
            "sway = { damping = 0 }",
            "layer[0].species[0].sway.damping: 0 is out of range",
        ),
        ("sway = { springiness = 2 }", "springiness"),
    ] {
        let error = parse(&format!("{layer}{bad}\n")).unwrap_err().to_string();
        assert!(error.contains(says), "{bad}: {error}");
    }
}

#[test]
fn explicit_plants_are_read_and_bad_ones_are_refused_by_key() {
    let good = parse(
        "preset = \"meadow\"\n[[plant]]\nspecies = \"meadow grass 1\"\nlayer = 0\ntranslation = [1, 2, 3]\nrotation = [0, 0, 0, 1]\nscale = [2, 2, 2]\n",
    )
    .unwrap();
    let plants = good.spec.plants.unwrap();
    assert_eq!(plants.len(), 1);
    assert_eq!(plants[0].transform.translation, Vec3::new(1.0, 2.0, 3.0));
    for (bad, why) in [
        (
            "rotation = [0, 0, 0, 2]\nscale = [1, 1, 1]\nlayer = 0",
            "unit rotation",
        ),
        (
            "rotation = [0, 0, 0, 1]\nscale = [0, 1, 1]\nlayer = 0",
            "positive scale",
        ),
        (
            "rotation = [0, 0, 0, 1]\nscale = [1, 1, 1]\nlayer = 9",
            "layer 9",
        ),
    ] {
        let text = format!(
            "preset = \"meadow\"\n[[plant]]\nspecies = \"a\"\ntranslation = [0, 0, 0]\n{bad}\n"
        );
        let error = parse(&text).unwrap_err().to_string();
        assert!(error.contains("plant[0]") && error.contains(why), "{error}");
    }
}

#[test]
fn errors_name_file_line_and_key() {
    let cases = [
        (
            "[terrain]\nsize = 10\nbumpiness = 3\n",
            "my.toml:3:1",
            "bumpiness",
        ),
        (
            "[terrain]\ncells = \"many\"\n",
            "my.toml:2:9: terrain.cells",
            "u32",
        ),
        (
            "[terrain]\ncells = 5000\n",
            "my.toml:2:9: terrain.cells",
            "out of range",
        ),
        (
            "preset = \"jungle\"\n",
            "my.toml:1:10: preset",
            "meadow, forest, paper",
        ),
        (
            "[[layer]]\nname = \"a\"\ncount = 3\n[[layer.species]]\nname = \"x\"\nkind = \"tre\"\n",
            "my.toml:6:8: layer[0].species[0].kind",
            "unknown kind 'tre'",
        ),
        (
            "[[layer]]\nname = \"a\"\ncount = 3\nspecies = []\n",
            "layer[0].species",
            "at least one species",
        ),
        (
            "[[layer]]\nname = \"a\"\ncount = 3\nscale = [2, 1]\nspecies = []\n",
            "my.toml:4:9: layer[0].scale",
            "low ≤ high",
        ),
        (
            "[sun]\nelevation = nan\nazimuth = 0\n",
            "my.toml:2:13: sun.elevation",
            "out of range",
        ),
        (
            "[wind]\nspeed = -3\n",
            "my.toml:2:9: wind.speed",
            "out of range",
        ),
        (
            "[wind]\nspeed = 3\ngust_wavelength = 0\n",
            "my.toml:3:19: wind.gust_wavelength",
            "out of range",
        ),
        ("[wind]\ndirection = 90\n", "my.toml", "speed"),
        ("[terrain\n", "my.toml:1:", ""),
        (
            "[sky]\nturbidity = 3\nzenith = [0, 0, 1]\n",
            "my.toml: sky",
            "either",
        ),
        (
            "[sky]\nturbidity = 30\n",
            "my.toml:2:13: sky.turbidity",
            "out of range",
        ),
    ];
    for (text, place, what) in cases {
        let e = parse(text).unwrap_err().to_string();
        assert!(e.contains(place) && e.contains(what), "{text:?} gave: {e}");
    }
    let missing = SceneFile::load(Path::new("/nonexistent/scene.toml")).unwrap_err();
    assert!(
        missing.to_string().contains("/nonexistent/scene.toml"),
        "{missing}"
    );
}

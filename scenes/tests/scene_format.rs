//! The scene format's reference (`docs/scene-format.md`) against the parser: its example
//! parses, and it names every key the parser reads, so a key added to the parser without
//! a word in the reference fails here.

use std::path::Path;
use sylva_scenes::scene_file::SceneFile;

fn reference() -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/scene-format.md");
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The reference's ```toml block.
fn example(reference: &str) -> &str {
    let start = reference.find("```toml\n").expect("a toml block") + "```toml\n".len();
    let end = start + reference[start..].find("```").expect("the block ends");
    &reference[start..end]
}

/// Every field of the parser's tables: the `pub(super) NAME:` lines of its document
/// structs.
fn parser_keys() -> Vec<String> {
    let source = include_str!("../src/scene_file/document.rs");
    let mut keys: Vec<String> = source
        .lines()
        .filter_map(|line| line.trim().strip_prefix("pub(super) "))
        .filter_map(|rest| rest.split_once(':'))
        .map(|(name, _)| name.trim().to_owned())
        .filter(|name| !name.contains(' '))
        .collect();
    keys.sort();
    keys.dedup();
    keys
}

#[test]
fn the_reference_example_parses() {
    let reference = reference();
    let file = SceneFile::parse(example(&reference), Path::new("docs/scene-format.md"))
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(file.seed, Some(7));
    assert_eq!(file.spec.name, "my meadow");
    assert_eq!(file.spec.layers.len(), 1);
    assert_eq!(
        file.spec.layers[0].species.len(),
        5,
        "two species and three variants"
    );
    assert!(file.spec.wind.is_some() && file.spec.camera_path.is_some());
    assert_eq!(file.spec.plants.as_ref().map(Vec::len), Some(1));
}

#[test]
fn the_reference_names_every_key_the_parser_reads() {
    let reference = reference();
    let keys = parser_keys();
    assert!(keys.len() > 40, "only {} keys found: {keys:?}", keys.len());
    let missing: Vec<&String> = keys
        .iter()
        .filter(|key| {
            // As a key (`key =`, also inside comments and inline tables) or a table
            // header (`[key]`, `[[key]]`, `[[layer.key]]`).
            !reference.contains(&format!("{key} ="))
                && !reference.contains(&format!("[{key}]"))
                && !reference.contains(&format!(".{key}]"))
        })
        .collect();
    assert!(
        missing.is_empty(),
        "keys without a word in the reference: {missing:?}"
    );
}

#[test]
fn every_built_in_preset_is_a_scene_file_that_parses() {
    for &name in sylva_scenes::SCENE_NAMES {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("files/{name}.toml"));
        let file = SceneFile::load(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(file.spec.name, name);
        assert_eq!(Some(file.spec), sylva_scenes::scene_file::preset(name));
    }
    assert_eq!(sylva_scenes::scene_file::preset("moor"), None);
}

#[test]
fn a_height_range_and_variants_go_together() {
    let file = |species: &str| {
        format!(
            "[[layer]]\nname = \"l\"\ncount = 1\n[[layer.species]]\nname = \"s\"\nkind = \"herb\"\n{species}"
        )
    };
    let error = |species: &str| {
        SceneFile::parse(&file(species), Path::new("v.toml"))
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default()
    };
    let range_alone = error("height = [0.3, 0.5]\n");
    assert!(
        range_alone.contains("layer[0].species[0].height") && range_alone.contains("variants"),
        "{range_alone}"
    );
    let variants_alone = error("variants = 3\nheight = 0.4\n");
    assert!(
        variants_alone.contains("layer[0].species[0].height"),
        "{variants_alone}"
    );
    let no_height = error("variants = 3\n");
    assert!(
        no_height.contains("layer[0].species[0].variants"),
        "{no_height}"
    );
    let backwards = error("variants = 3\nheight = [0.5, 0.3]\n");
    assert!(backwards.contains("low ≤ high"), "{backwards}");
    let family = SceneFile::parse(
        &file("variants = 3\nheight = [0.3, 0.5]\n"),
        Path::new("v.toml"),
    )
    .unwrap();
    let names: Vec<&str> = family.spec.layers[0]
        .species
        .iter()
        .map(|s| s.name.as_str())
        .collect();
    assert_eq!(names, ["s 1", "s 2", "s 3"]);
}

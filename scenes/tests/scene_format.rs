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
    assert_eq!(file.spec.layers[0].species.len(), 2);
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

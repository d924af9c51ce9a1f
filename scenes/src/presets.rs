//! The built-in ecosystems, `meadow`, `forest` and `paper`, as scene files compiled into
//! the binary: `scenes/files/NAME.toml` in the format users write (and so its fullest
//! examples), parsed by [`scene_file::preset`](crate::scene_file::preset).

/// Names of the presets.
pub const PRESETS: &[&str] = &["meadow", "forest", "paper"];

/// The scene file of preset `name`.
pub(crate) fn text(name: &str) -> Option<&'static str> {
    match name {
        "meadow" => Some(include_str!("../files/meadow.toml")),
        "forest" => Some(include_str!("../files/forest.toml")),
        "paper" => Some(include_str!("../files/paper.toml")),
        _ => None,
    }
}

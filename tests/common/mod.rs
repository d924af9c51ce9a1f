//! What the end-to-end test crates share.

use std::collections::HashMap;
use std::path::Path;

/// The tEXt chunks of a PNG as keyword → text.
pub fn png_text(path: &Path) -> HashMap<String, String> {
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())),
    ));
    let reader = decoder.read_info().unwrap();
    reader
        .info()
        .uncompressed_latin1_text
        .iter()
        .map(|t| (t.keyword.clone(), t.text.clone()))
        .collect()
}

//! glTF images: embedded, `data:` URI or file, decoded with their size checked before
//! decoding.

use super::*;

/// Minimal base64 (RFC 4648) for `data:` image URIs.
pub(super) fn base64_decode(text: &str) -> Option<Vec<u8>> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => Some(c - b'A'),
        b'a'..=b'z' => Some(c - b'a' + 26),
        b'0'..=b'9' => Some(c - b'0' + 52),
        b'+' | b'-' => Some(62),
        b'/' | b'_' => Some(63),
        _ => None,
    };
    let clean: Vec<u8> = text
        .bytes()
        .filter(|&c| c != b'=' && !c.is_ascii_whitespace())
        .collect();
    let mut out = Vec::with_capacity(clean.len() * 3 / 4);
    for chunk in clean.chunks(4) {
        let v: Vec<u8> = chunk.iter().map(|&c| value(c)).collect::<Option<_>>()?;
        let n = v
            .iter()
            .enumerate()
            .fold(0u32, |n, (i, &x)| n | (x as u32) << (18 - 6 * i));
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    Some(out)
}

/// Where an image's bytes are.
pub(super) enum ImageSource<'a> {
    View(gltf::buffer::View<'a>),
    Uri(&'a str),
}

pub(super) fn decode_image(
    importer: &Importer,
    image: &gltf::Image,
    base: &Path,
    role: &str,
) -> Result<Texture, GltfError> {
    let at = format!("images[{}] ({role})", image.index());
    // Read the source from the JSON: gltf's `Image::source` unwraps a missing uri, a
    // missing mimeType beside a bufferView, and a bufferView index out of range.
    let raw = &importer.document.as_json().images[image.index()];
    let source = match (&raw.buffer_view, &raw.uri) {
        (Some(view), _) => {
            let view = importer
                .document
                .views()
                .nth(view.value())
                .ok_or_else(|| importer.error(at.clone(), "bufferView index out of range"))?;
            ImageSource::View(view)
        }
        (None, Some(uri)) => ImageSource::Uri(uri.as_str()),
        (None, None) => {
            return Err(importer.error(at, "the image has neither a uri nor a bufferView"));
        }
    };
    let bytes: Vec<u8> = match source {
        ImageSource::View(view) => {
            let data = importer
                .buffers
                .get(view.buffer().index())
                .and_then(|b| b.0.get(view.offset()..view.offset() + view.length()))
                .ok_or_else(|| importer.error(at.clone(), "buffer view out of range"))?;
            data.to_vec()
        }
        ImageSource::Uri(uri) => {
            if let Some(rest) = uri.strip_prefix("data:") {
                let payload = rest.split_once(";base64,").map(|(_, p)| p);
                payload
                    .and_then(base64_decode)
                    .ok_or_else(|| importer.error(at.clone(), "malformed data: URI"))?
            } else {
                let file = base.join(uri);
                std::fs::read(&file).map_err(|e| {
                    importer.error(at.clone(), format!("cannot read '{}': {e}", file.display()))
                })?
            }
        }
    };
    decode_texture(&bytes).map_err(|message| importer.error(at, message))
}

/// Decodes a PNG or JPEG texture (sRGB colour, grey + alpha kept as such), checking its
/// dimensions (edges 1 … `MAX_TEXTURE_EDGE`) before allocating for its pixels.
pub fn decode_texture(bytes: &[u8]) -> Result<Texture, String> {
    let reader = || {
        image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| e.to_string())
    };
    let (width, height) = reader()?
        .into_dimensions()
        .map_err(|e| format!("cannot decode image: {e}"))?;
    if width == 0 || height == 0 || width > MAX_TEXTURE_EDGE || height > MAX_TEXTURE_EDGE {
        return Err(format!(
            "image is {width}×{height}; edges must lie in 1 … {MAX_TEXTURE_EDGE}"
        ));
    }
    let decoded = reader()?
        .decode()
        .map_err(|e| format!("cannot decode image: {e}"))?;
    let texture = match decoded {
        image::DynamicImage::ImageLumaA8(img) => {
            let texels: Vec<[u8; 2]> = img.pixels().map(|p| p.0).collect();
            Texture::from_gray_alpha8(width, height, &texels)
        }
        other => {
            let rgba = other.to_rgba8();
            Texture::from_srgba8(width, height, rgba.pixels().map(|p| p.0).collect())
        }
    };
    texture.map_err(|e| e.to_string())
}

//! PNG encoding.

/// An 8-bit RGB image (`w` x `h`, rows top to bottom, 3 bytes per pixel) as PNG bytes.
pub fn encode_rgb(w: u32, h: u32, rgb: &[u8]) -> anyhow::Result<Vec<u8>> {
    encode(w, h, png::ColorType::Rgb, rgb)
}

/// An 8-bit grayscale image (`w` x `h`, rows top to bottom, 1 byte per pixel) as PNG bytes.
pub fn encode_gray(w: u32, h: u32, gray: &[u8]) -> anyhow::Result<Vec<u8>> {
    encode(w, h, png::ColorType::Grayscale, gray)
}

fn encode(w: u32, h: u32, color: png::ColorType, pixels: &[u8]) -> anyhow::Result<Vec<u8>> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(color);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc.write_header()?;
    writer.write_image_data(pixels)?;
    writer.finish()?;
    Ok(out)
}

//! PNG encoding.

/// An 8-bit RGB image (`w` x `h`, rows top to bottom, 3 bytes per pixel) as PNG bytes.
pub fn encode_rgb(w: u32, h: u32, rgb: &[u8]) -> anyhow::Result<Vec<u8>> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc.write_header()?;
    writer.write_image_data(rgb)?;
    writer.finish()?;
    Ok(out)
}

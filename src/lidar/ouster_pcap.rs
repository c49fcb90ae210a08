//! Decoder for Ouster lidar PCAP captures into organized point clouds.
//!
//! Ouster sensors stream one UDP datagram per group of `columns_per_packet`
//! azimuth columns; a capture of that stream plus the sensor's metadata JSON
//! is the usual way Ouster data is shared. This module turns such a capture
//! into one [`Scan`] per rotation without the C++ SDK, using only `std` and
//! `serde_json`.
//!
//! # Pipeline
//! 1. `pcap` submodule: classic pcap records (µs/ns, either byte order;
//!    pcapng is refused) -> Ethernet / Linux cooked / raw IP -> IPv4
//!    (fragments reassembled, e.g. OS-2-128's 24832-byte packets) or IPv6
//!    -> UDP.
//! 2. Datagrams to `udp_port_lidar` are lidar packets; their size must match
//!    the profile exactly, otherwise decoding would read garbage, so a
//!    mismatch is an error. 48-byte (IMU-sized) payloads and other ports are
//!    skipped.
//! 3. Columns are grouped by `frame_id` in packet order; a frame is emitted
//!    when the id changes and at end of file. [`OusterFrame::columns_seen`]
//!    tells complete rotations from the partial first/last ones. Late
//!    packets of a previous frame are not re-merged (the SDK drops them);
//!    they show up as an extra partial frame.
//!
//! # Output layout
//! The cloud is organized: `height` = beams, `width` = `columns_per_frame`,
//! index = `row * width + col`, row 0 = `beam_altitude_angles[0]` (top beam).
//! Pixels arrive *staggered*: each beam points `beam_azimuth_angles[r]`
//! degrees away from the encoder angle, so the packet column with
//! measurement id `m` holds, for row `r`, light from direction
//! `θ_enc(m) − azimuth[r]`. The encoder angle decreases by `360/W` per
//! column, so a beam with azimuth `a` sees at `m` what an `a = 0` beam sees
//! at `m + a·W/360`. Destaggering (Ouster SDK convention) therefore stores
//! the pixel at column `(m + pixel_shift_by_row[r]) mod W`, the shift table
//! being `a·W/360` up to a constant; a vertical pole then lands in a single
//! column. Cells with no return (range 0) and columns never received are
//! `[0, 0, 0]`, with intensity 0 and time 0.
//!
//! # Geometry (Ouster firmware user manual, "lidar range to XYZ")
//! With `r` the range in mm, `n` = `lidar_origin_to_beam_origin_mm`,
//! `θ_enc = 2π(1 − m/W)`, `θ_az = −2π·azimuth/360`, `φ = 2π·altitude/360`:
//! `x = (r−n)cos(θ_enc+θ_az)cosφ + n·cosθ_enc`,
//! `y = (r−n)sin(θ_enc+θ_az)cosφ + n·sinθ_enc`, `z = (r−n)sinφ`; then
//! `lidar_to_sensor_transform` (mm) is applied and the result is scaled to
//! meters. The angle terms are precomputed once per capture (`Lut`).

mod metadata;
mod pcap;
#[cfg(test)]
mod tests;

pub use metadata::{OusterMetadata, UdpProfile};

use std::collections::BTreeMap;

use crate::lidar::scan::Scan;
use pcap::{Datagram, PcapReader};

/// IMU packets are always this size; tolerated even on the lidar port.
const IMU_PACKET_SIZE: usize = 48;

/// Everything that can go wrong; every variant carries enough context
/// (byte offset, record index) to find the culprit in the file.
#[derive(Debug, thiserror::Error)]
pub enum OusterError {
    #[error("metadata is not valid JSON: {0}")]
    Json(#[from] serde_json::Error),
    #[error("invalid Ouster metadata: {0}")]
    Metadata(String),
    #[error("pcapng is not supported; convert with `editcap -F pcap in.pcapng out.pcap`")]
    PcapNg,
    #[error("malformed pcap at byte offset {offset}: {msg}")]
    Pcap { offset: usize, msg: String },
    #[error(
        "lidar packet in pcap record {record_index} (byte offset {offset}) has {actual} bytes; \
         profile {profile} with the metadata's layout needs {expected}"
    )]
    PacketSize {
        record_index: usize,
        offset: usize,
        actual: usize,
        expected: usize,
        profile: &'static str,
    },
}

impl OusterError {
    /// Whether nothing after this error can be read (damage to the pcap's own records, as
    /// opposed to one bad packet that [`frames`] skips).
    pub fn ends_capture(&self) -> bool {
        matches!(self, OusterError::Pcap { .. })
    }
}

/// One rotation (or the part of it present in the capture).
#[derive(Debug, Clone, PartialEq)]
pub struct OusterFrame {
    pub frame_id: u32,
    /// Sensor timestamp (ns) of the first valid column received (0 if none).
    pub timestamp_ns: u64,
    /// Organized cloud, `height` = beams, `width` = `columns`.
    pub scan: Scan,
    /// Distinct valid columns received; less than `columns` = partial frame.
    pub columns_seen: usize,
    /// Columns per frame from the metadata.
    pub columns: usize,
    /// Valid columns whose measurement id lies past `columns` (metadata that does not match
    /// the capture): their returns are not in the scan.
    pub columns_beyond: usize,
}

impl OusterFrame {
    /// True when every column of the rotation was received.
    pub fn is_complete(&self) -> bool {
        self.columns_seen == self.columns
    }
}

/// Decodes a whole capture. Holds every frame in memory (≈ 2.9 MB per
/// 128x1024 frame); use [`frames`] to stream long captures instead.
pub fn read_pcap(
    pcap_bytes: &[u8],
    meta: &OusterMetadata,
) -> Result<Vec<OusterFrame>, OusterError> {
    frames(pcap_bytes, meta)?.collect()
}

/// Streams frames one at a time, so memory stays bounded by one frame
/// regardless of how many (possibly hostile) frame ids the capture holds.
pub fn frames<'a>(
    pcap_bytes: &'a [u8],
    meta: &'a OusterMetadata,
) -> Result<OusterFrames<'a>, OusterError> {
    // The fields are public, so re-check what decoding indexes by.
    meta.validate()?;
    Ok(OusterFrames {
        reader: PcapReader::new(pcap_bytes)?,
        layout: PacketLayout::new(meta),
        lut: Lut::new(meta),
        meta,
        current: None,
        cut_off: false,
        finished: false,
        lidar_packets: 0,
        other_ports: BTreeMap::new(),
    })
}

/// Iterator returned by [`frames`]. Damage costs no more than it touches: a bad lidar packet
/// is an error item and reading goes on after it; damage to the pcap's records (a capture cut
/// off mid-record) is an error item, then the rotation in progress as a partial frame, then
/// the end.
pub struct OusterFrames<'a> {
    reader: PcapReader<'a>,
    layout: PacketLayout,
    lut: Lut,
    meta: &'a OusterMetadata,
    current: Option<FrameBuilder>,
    /// The pcap's records are damaged: nothing after the rotation in progress can be read.
    cut_off: bool,
    finished: bool,
    /// Lidar packets read so far.
    lidar_packets: usize,
    /// Datagrams of a lidar packet's size on other ports than the metadata's, per port.
    other_ports: BTreeMap<u16, usize>,
}

impl Iterator for OusterFrames<'_> {
    type Item = Result<OusterFrame, OusterError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.finished {
            return None;
        }
        if self.cut_off {
            self.finished = true;
            return self.finish_current().map(Ok);
        }
        match self.advance() {
            Ok(Some(frame)) => Some(Ok(frame)),
            Ok(None) => {
                self.finished = true;
                None
            }
            Err(e) => {
                self.cut_off = e.ends_capture();
                Some(Err(e))
            }
        }
    }
}

impl OusterFrames<'_> {
    /// Where no lidar packet was read although packets of a lidar packet's size went to other
    /// ports: which port the metadata names and which the packets use.
    pub fn port_mismatch(&self) -> Option<String> {
        if self.lidar_packets > 0 || self.other_ports.is_empty() {
            return None;
        }
        let ports: Vec<String> = self
            .other_ports
            .iter()
            .map(|(port, n)| format!("{port} ({n} packets)"))
            .collect();
        Some(format!(
            "no lidar packet went to UDP port {} (the metadata's udp_port_lidar); packets of the lidar packet size ({} bytes) went to port {}",
            self.meta.udp_port_lidar,
            self.layout.size,
            ports.join(", ")
        ))
    }

    fn finish_current(&mut self) -> Option<OusterFrame> {
        self.current.take().map(|b| b.finish(&self.lut, self.meta))
    }

    /// Feeds packets until a frame is complete (id change or end of file).
    fn advance(&mut self) -> Result<Option<OusterFrame>, OusterError> {
        while let Some(datagram) = self.reader.next_datagram()? {
            let Some(packet) = self.lidar_payload(&datagram)? else {
                if datagram.payload.len() == self.layout.size {
                    *self.other_ports.entry(datagram.dst_port).or_default() += 1;
                }
                continue;
            };
            self.lidar_packets += 1;
            let frame_id = self.layout.frame_id(packet);
            let done = match self.current.take() {
                Some(b) if b.frame_id != frame_id => Some(b),
                Some(b) => {
                    self.current = Some(b);
                    None
                }
                None => None,
            };
            let builder = self
                .current
                .get_or_insert_with(|| FrameBuilder::new(frame_id, self.meta));
            builder.add_packet(&self.layout, packet);
            if let Some(b) = done {
                return Ok(Some(b.finish(&self.lut, self.meta)));
            }
        }
        Ok(self.finish_current())
    }

    /// The payload if this datagram is a lidar packet, `None` to skip it,
    /// an error if it is addressed as lidar data but has the wrong size.
    fn lidar_payload<'d>(&self, d: &'d Datagram<'_>) -> Result<Option<&'d [u8]>, OusterError> {
        let expected = self.layout.size;
        let actual = d.payload.len();
        let any_port = self.meta.udp_port_lidar == 0;
        if any_port {
            return Ok((actual == expected).then_some(&d.payload[..]));
        }
        if d.dst_port != self.meta.udp_port_lidar || actual == IMU_PACKET_SIZE {
            return Ok(None);
        }
        if actual != expected {
            return Err(OusterError::PacketSize {
                record_index: d.record_index,
                offset: d.record_offset,
                actual,
                expected,
                profile: self.meta.udp_profile_lidar.name(),
            });
        }
        Ok(Some(&d.payload[..]))
    }
}

/// Byte layout of one lidar packet, derived once from the metadata.
struct PacketLayout {
    profile: UdpProfile,
    packet_header: usize,
    col_header: usize,
    col_size: usize,
    columns_per_packet: usize,
    pixels_per_column: usize,
    bytes_per_pixel: usize,
    size: usize,
}

/// Header fields of one column plus its pixel bytes.
struct Column<'p> {
    timestamp_ns: u64,
    measurement_id: usize,
    valid: bool,
    pixels: &'p [u8],
}

fn le16(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}

fn le32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

fn le64(b: &[u8], at: usize) -> u64 {
    let mut w = [0u8; 8];
    w.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(w)
}

impl PacketLayout {
    fn new(meta: &OusterMetadata) -> Self {
        let profile = meta.udp_profile_lidar;
        let (packet_header, col_header, col_footer, _) = profile.framing();
        let bytes_per_pixel = profile.bytes_per_pixel();
        Self {
            profile,
            packet_header,
            col_header,
            col_size: col_header + meta.pixels_per_column * bytes_per_pixel + col_footer,
            columns_per_packet: meta.columns_per_packet,
            pixels_per_column: meta.pixels_per_column,
            bytes_per_pixel,
            size: meta.lidar_packet_size(),
        }
    }

    /// eUDP: u16 at byte 2 of the packet header. LEGACY has no packet
    /// header; every column repeats the id at byte 10, column 0's is used.
    /// The caller guarantees `packet.len() == self.size`.
    fn frame_id(&self, packet: &[u8]) -> u32 {
        match self.profile {
            UdpProfile::Legacy => u32::from(le16(packet, 10)),
            _ => u32::from(le16(packet, 2)),
        }
    }

    /// Column header: timestamp u64 @0, measurement id u16 @8; status is
    /// u16 @10 (eUDP) or the u32 column footer (LEGACY, all ones = valid).
    /// Bit 0 of status marks a valid column in both.
    fn column<'p>(&self, packet: &'p [u8], i: usize) -> Column<'p> {
        let start = self.packet_header + i * self.col_size;
        let col = &packet[start..start + self.col_size];
        let status = match self.profile {
            UdpProfile::Legacy => le32(col, self.col_size - 4),
            _ => u32::from(le16(col, 10)),
        };
        let pixel_bytes = self.pixels_per_column * self.bytes_per_pixel;
        Column {
            timestamp_ns: le64(col, 0),
            measurement_id: usize::from(le16(col, 8)),
            valid: status & 1 == 1,
            pixels: &col[self.col_header..self.col_header + pixel_bytes],
        }
    }

    /// (range mm, reflectivity) of one pixel; field offsets/masks follow
    /// Ouster's published per-profile tables.
    fn pixel(&self, px: &[u8]) -> (u32, u16) {
        match self.profile {
            // range u32 low 20 bits; reflectivity u16 @4; signal @6; NIR @8.
            UdpProfile::Legacy => (le32(px, 0) & 0x000F_FFFF, le16(px, 4)),
            // range u32 low 19 bits; reflectivity u8 @4; signal @6; NIR @8.
            UdpProfile::Rng19Rfl8Sig16Nir16 => (le32(px, 0) & 0x0007_FFFF, u16::from(px[4])),
            // range u16 low 15 bits in 8 mm units; reflectivity @2; NIR @3.
            UdpProfile::Rng15Rfl8Nir8 => (u32::from(le16(px, 0) & 0x7FFF) * 8, u16::from(px[2])),
            // first return: range u32 low 19 bits; reflectivity u8 @3.
            UdpProfile::Rng19Rfl8Sig16Nir16Dual => (le32(px, 0) & 0x0007_FFFF, u16::from(px[3])),
        }
    }
}

/// Raw (still staggered) data of the frame being assembled, indexed
/// `row * W + measurement_id`; destaggering happens once in [`finish`].
///
/// [`finish`]: FrameBuilder::finish
struct FrameBuilder {
    frame_id: u32,
    width: usize,
    range_mm: Vec<u32>,
    reflectivity: Vec<u16>,
    column_ts: Vec<u64>,
    column_seen: Vec<bool>,
    columns_seen: usize,
    columns_beyond: usize,
    first_ts: Option<u64>,
}

impl FrameBuilder {
    fn new(frame_id: u32, meta: &OusterMetadata) -> Self {
        let (w, h) = (meta.columns_per_frame, meta.pixels_per_column);
        Self {
            frame_id,
            width: w,
            range_mm: vec![0; w * h],
            reflectivity: vec![0; w * h],
            column_ts: vec![0; w],
            column_seen: vec![false; w],
            columns_seen: 0,
            columns_beyond: 0,
            first_ts: None,
        }
    }

    /// Copies every valid column. Invalid columns are dropped, as the SDK does, and so are
    /// measurement ids beyond the frame width (metadata that does not match the capture),
    /// which are counted; a repeated column overwrites the earlier copy.
    fn add_packet(&mut self, layout: &PacketLayout, packet: &[u8]) {
        for i in 0..layout.columns_per_packet {
            let col = layout.column(packet, i);
            let m = col.measurement_id;
            if !col.valid {
                continue;
            }
            if m >= self.width {
                self.columns_beyond += 1;
                continue;
            }
            self.first_ts.get_or_insert(col.timestamp_ns);
            self.column_ts[m] = col.timestamp_ns;
            if !self.column_seen[m] {
                self.column_seen[m] = true;
                self.columns_seen += 1;
            }
            let pixels = col.pixels.chunks_exact(layout.bytes_per_pixel);
            for (row, px) in pixels.enumerate() {
                let (range, refl) = layout.pixel(px);
                self.range_mm[row * self.width + m] = range;
                self.reflectivity[row * self.width + m] = refl;
            }
        }
    }

    /// Destaggers, projects to XYZ and packs the [`Scan`].
    fn finish(self, lut: &Lut, meta: &OusterMetadata) -> OusterFrame {
        let (w, h) = (self.width, meta.pixels_per_column);
        let first = self.first_ts.unwrap_or(0);
        let mut xyz = vec![[0.0f32; 3]; w * h];
        let mut intensity = vec![0.0f32; w * h];
        let mut time_s = vec![0.0f32; w * h];
        let ring = (0..h)
            .flat_map(|r| std::iter::repeat_n(r as u16, w))
            .collect();
        for (row, &shift) in meta.pixel_shift_by_row.iter().enumerate() {
            for m in 0..w {
                let src = row * w + m;
                let dst = row * w + destaggered_column(m, shift, w);
                if self.column_seen[m] {
                    time_s[dst] =
                        ((self.column_ts[m] as i128 - first as i128) as f64 * 1e-9) as f32;
                }
                intensity[dst] = f32::from(self.reflectivity[src]);
                xyz[dst] = lut.point(src, self.range_mm[src]);
            }
        }
        OusterFrame {
            frame_id: self.frame_id,
            timestamp_ns: first,
            scan: Scan {
                xyz,
                intensity: Some(intensity),
                ring: Some(ring),
                time_s: Some(time_s),
                label: None,
                height: h,
                width: w,
            },
            columns_seen: self.columns_seen,
            columns: w,
            columns_beyond: self.columns_beyond,
        }
    }
}

/// Ouster destagger: measurement id `m` of a row shifted by `shift` goes to
/// column `(m + shift) mod w` (shift may be negative in metadata).
fn destaggered_column(m: usize, shift: i32, w: usize) -> usize {
    let w_i = w as i64;
    (m as i64 + i64::from(shift)).rem_euclid(w_i) as usize
}

/// Per-(row, measurement id) unit direction and offset in the sensor frame
/// (mm), so a point is `range * dir + offset`: the trigonometry and the
/// lidar-to-sensor transform are evaluated once per capture, not per point.
struct Lut {
    dir: Vec<[f64; 3]>,
    offset: Vec<[f64; 3]>,
}

impl Lut {
    fn new(meta: &OusterMetadata) -> Self {
        let (w, h) = (meta.columns_per_frame, meta.pixels_per_column);
        let t = &meta.lidar_to_sensor_transform;
        let rotate = |v: [f64; 3]| {
            [0, 1, 2].map(|i| t[4 * i] * v[0] + t[4 * i + 1] * v[1] + t[4 * i + 2] * v[2])
        };
        let n = meta.lidar_origin_to_beam_origin_mm;
        let z0 = meta.beam_origin_z_mm;
        // With a vertical offset the beam origin is off-axis; the SDK then
        // uses the Euclidean distance to the origin as the range correction.
        let dist = if z0 == 0.0 { n } else { n.hypot(z0) };
        let mut lut = Self {
            dir: Vec::with_capacity(w * h),
            offset: Vec::with_capacity(w * h),
        };
        for row in 0..h {
            let phi = meta.beam_altitude_angles[row].to_radians();
            let az = -meta.beam_azimuth_angles[row].to_radians();
            for m in 0..w {
                let enc = 2.0 * std::f64::consts::PI * (1.0 - m as f64 / w as f64);
                let d = [
                    (enc + az).cos() * phi.cos(),
                    (enc + az).sin() * phi.cos(),
                    phi.sin(),
                ];
                let o = [
                    n * enc.cos() - d[0] * dist,
                    n * enc.sin() - d[1] * dist,
                    z0 - d[2] * dist,
                ];
                let o = rotate(o);
                lut.dir.push(rotate(d));
                lut.offset.push([o[0] + t[3], o[1] + t[7], o[2] + t[11]]);
            }
        }
        lut
    }

    /// Point in meters; range 0 means "no return" and maps to the origin.
    fn point(&self, index: usize, range_mm: u32) -> [f32; 3] {
        if range_mm == 0 {
            return [0.0; 3];
        }
        let r = f64::from(range_mm);
        let (d, o) = (self.dir[index], self.offset[index]);
        [0, 1, 2].map(|i| ((r * d[i] + o[i]) * 1e-3) as f32)
    }
}

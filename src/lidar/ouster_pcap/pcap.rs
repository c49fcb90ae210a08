//! Classic-pcap record walking, link/IP/UDP unwrapping and IPv4 fragment
//! reassembly, reduced to exactly what lidar captures need.
//!
//! Only UDP matters here, so anything else (TCP, ARP, IPv6 extension
//! headers, ...) is skipped rather than rejected: captures routinely contain
//! unrelated traffic. Structural damage to the *file* (bad magic, truncated
//! or absurd records) is an error, because continuing would mean guessing.

use std::borrow::Cow;
use std::collections::VecDeque;

use super::OusterError;

/// Largest record we accept. Ouster payloads are < 64 KiB; anything bigger
/// is a corrupt length field, and refusing it bounds memory.
pub(crate) const MAX_RECORD_LEN: usize = 256 * 1024;
/// Reassembly buffers kept at once (a lidar sends one datagram at a time;
/// a few extra tolerate interleaved IMU/other traffic).
const MAX_PARTIALS: usize = 16;
/// Fragments per datagram; 24832 bytes at a 576-byte MTU needs ~45.
const MAX_FRAGMENTS: usize = 128;
/// IPv4 total length is 16 bits, minus the minimum 20-byte header.
const MAX_IPV4_PAYLOAD: usize = 65_535 - 20;

const PCAP_HEADER_LEN: usize = 24;
const RECORD_HEADER_LEN: usize = 16;
const PCAPNG_MAGIC: u32 = 0x0A0D_0D0A;

/// One UDP datagram pulled out of the capture.
#[derive(Debug)]
pub(crate) struct Datagram<'a> {
    /// Index (0-based) of the pcap record that completed the datagram.
    pub record_index: usize,
    /// Byte offset of that record's header in the file.
    pub record_offset: usize,
    pub dst_port: u16,
    /// Borrowed for whole packets, owned when reassembled from fragments.
    pub payload: Cow<'a, [u8]>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Link {
    /// DLT_NULL: 4-byte address family in the writer's byte order.
    Null,
    Ethernet,
    /// Bare IP; the version nibble tells v4 from v6.
    Raw,
    LinuxSll,
    LinuxSll2,
}

impl Link {
    fn from_linktype(linktype: u32) -> Option<Self> {
        match linktype {
            0 => Some(Self::Null),
            1 => Some(Self::Ethernet),
            12 | 101 | 228 | 229 => Some(Self::Raw),
            113 => Some(Self::LinuxSll),
            276 => Some(Self::LinuxSll2),
            _ => None,
        }
    }
}

/// Network-layer packet after the link header is stripped.
enum Network<'a> {
    V4(&'a [u8]),
    V6(&'a [u8]),
}

fn pcap_err(offset: usize, msg: impl Into<String>) -> OusterError {
    OusterError::Pcap {
        offset,
        msg: msg.into(),
    }
}

fn be16(b: &[u8], at: usize) -> u16 {
    u16::from_be_bytes([b[at], b[at + 1]])
}

/// One pcap record: its index, header offset and captured bytes.
struct Record<'a> {
    index: usize,
    offset: usize,
    frame: &'a [u8],
}

/// Walks the records of a classic pcap held in memory.
pub(crate) struct PcapReader<'a> {
    data: &'a [u8],
    offset: usize,
    big_endian: bool,
    link: Link,
    record_index: usize,
    reassembler: Reassembler,
}

impl<'a> PcapReader<'a> {
    /// Validates the global header. pcapng is recognised and refused with a
    /// hint, because it is the most common "why doesn't this open" case.
    pub(crate) fn new(data: &'a [u8]) -> Result<Self, OusterError> {
        if data.len() < PCAP_HEADER_LEN {
            return Err(pcap_err(0, "file too short for a pcap global header"));
        }
        let magic_le = u32::from_le_bytes([data[0], data[1], data[2], data[3]]);
        let big_endian = match magic_le {
            0xA1B2_C3D4 | 0xA1B2_3C4D => false,
            0xD4C3_B2A1 | 0x4D3C_B2A1 => true,
            PCAPNG_MAGIC => return Err(OusterError::PcapNg),
            other => return Err(pcap_err(0, format!("unknown pcap magic {other:#010x}"))),
        };
        let mut reader = Self {
            data,
            offset: PCAP_HEADER_LEN,
            big_endian,
            link: Link::Ethernet,
            record_index: 0,
            reassembler: Reassembler::default(),
        };
        // The link type's upper bits carry FCS info in newer writers.
        let linktype = reader.u32_at(20) & 0x0FFF_FFFF;
        reader.link = Link::from_linktype(linktype)
            .ok_or_else(|| pcap_err(20, format!("unsupported pcap link type {linktype}")))?;
        Ok(reader)
    }

    fn u32_at(&self, at: usize) -> u32 {
        let b = [
            self.data[at],
            self.data[at + 1],
            self.data[at + 2],
            self.data[at + 3],
        ];
        if self.big_endian {
            u32::from_be_bytes(b)
        } else {
            u32::from_le_bytes(b)
        }
    }

    /// Next UDP datagram, `Ok(None)` at a clean end of file.
    pub(crate) fn next_datagram(&mut self) -> Result<Option<Datagram<'a>>, OusterError> {
        while let Some(record) = self.next_record()? {
            if let Some((dst_port, payload)) = self.unwrap_udp(record.frame) {
                return Ok(Some(Datagram {
                    record_index: record.index,
                    record_offset: record.offset,
                    dst_port,
                    payload,
                }));
            }
        }
        Ok(None)
    }

    /// Next record, `Ok(None)` exactly at end of file.
    fn next_record(&mut self) -> Result<Option<Record<'a>>, OusterError> {
        let start = self.offset;
        let remaining = self.data.len() - start;
        if remaining == 0 {
            return Ok(None);
        }
        let index = self.record_index;
        if remaining < RECORD_HEADER_LEN {
            return Err(pcap_err(
                start,
                format!("truncated header of record {index} ({remaining} of 16 bytes)"),
            ));
        }
        let incl_len = self.u32_at(start + 8) as usize;
        if incl_len > MAX_RECORD_LEN {
            return Err(pcap_err(
                start,
                format!("record {index} claims {incl_len} bytes (limit {MAX_RECORD_LEN})"),
            ));
        }
        let body = start + RECORD_HEADER_LEN;
        if incl_len > self.data.len() - body {
            return Err(pcap_err(
                start,
                format!(
                    "record {index} truncated: needs {incl_len} bytes, file has {}",
                    self.data.len() - body
                ),
            ));
        }
        self.offset = body + incl_len;
        self.record_index += 1;
        Ok(Some(Record {
            index,
            offset: start,
            frame: &self.data[body..body + incl_len],
        }))
    }

    fn unwrap_udp(&mut self, frame: &'a [u8]) -> Option<(u16, Cow<'a, [u8]>)> {
        match strip_link(self.link, self.big_endian, frame)? {
            Network::V4(ip) => self.ipv4_udp(ip),
            Network::V6(ip) => ipv6_udp(ip).map(|(p, d)| (p, Cow::Borrowed(d))),
        }
    }

    fn ipv4_udp(&mut self, ip: &'a [u8]) -> Option<(u16, Cow<'a, [u8]>)> {
        if ip.len() < 20 || ip[0] >> 4 != 4 {
            return None;
        }
        let ihl = usize::from(ip[0] & 0x0F) * 4;
        let total = usize::from(be16(ip, 2)).min(ip.len());
        if ihl < 20 || total < ihl || ip[9] != 17 {
            return None;
        }
        let body = &ip[ihl..total];
        let flags_frag = be16(ip, 6);
        let more = flags_frag & 0x2000 != 0;
        let frag_offset = usize::from(flags_frag & 0x1FFF) * 8;
        if !more && frag_offset == 0 {
            return udp_payload(body).map(|(p, d)| (p, Cow::Borrowed(d)));
        }
        let key = FragKey {
            src: [ip[12], ip[13], ip[14], ip[15]],
            dst: [ip[16], ip[17], ip[18], ip[19]],
            id: be16(ip, 4),
        };
        let mut whole = self.reassembler.push(key, frag_offset, more, body)?;
        let (port, len) = udp_payload(&whole).map(|(p, d)| (p, d.len()))?;
        // Reuse the reassembly buffer: drop the UDP header, keep the payload.
        whole.truncate(8 + len);
        whole.drain(..8);
        Some((port, Cow::Owned(whole)))
    }
}

/// Strips the link-layer header; `None` for non-IP frames.
fn strip_link(link: Link, big_endian: bool, frame: &[u8]) -> Option<Network<'_>> {
    let (ethertype, rest) = match link {
        Link::Ethernet => ethernet(frame)?,
        Link::LinuxSll => (be16(frame.get(..16)?, 14), &frame[16..]),
        Link::LinuxSll2 => (be16(frame.get(..20)?, 0), &frame[20..]),
        Link::Raw => return by_version(frame),
        Link::Null => {
            let fam = frame.get(..4)?;
            let fam = if big_endian {
                u32::from_be_bytes([fam[0], fam[1], fam[2], fam[3]])
            } else {
                u32::from_le_bytes([fam[0], fam[1], fam[2], fam[3]])
            };
            return match fam {
                2 => Some(Network::V4(&frame[4..])),
                24 | 28 | 30 => Some(Network::V6(&frame[4..])),
                _ => None,
            };
        }
    };
    match ethertype {
        0x0800 => Some(Network::V4(rest)),
        0x86DD => Some(Network::V6(rest)),
        _ => None,
    }
}

/// Ethernet II with up to two VLAN tags (802.1Q / 802.1ad).
fn ethernet(frame: &[u8]) -> Option<(u16, &[u8])> {
    let mut ethertype = be16(frame.get(..14)?, 12);
    let mut at = 14;
    for _ in 0..2 {
        if !matches!(ethertype, 0x8100 | 0x88A8 | 0x9100) {
            break;
        }
        ethertype = be16(frame.get(..at + 4)?, at + 2);
        at += 4;
    }
    Some((ethertype, &frame[at..]))
}

fn by_version(ip: &[u8]) -> Option<Network<'_>> {
    match ip.first()? >> 4 {
        4 => Some(Network::V4(ip)),
        6 => Some(Network::V6(ip)),
        _ => None,
    }
}

/// IPv6 with UDP directly after the fixed header (what sensors send).
fn ipv6_udp(ip: &[u8]) -> Option<(u16, &[u8])> {
    if ip.len() < 40 || ip[0] >> 4 != 6 || ip[6] != 17 {
        return None;
    }
    let end = (40 + usize::from(be16(ip, 4))).min(ip.len());
    udp_payload(&ip[40..end])
}

/// (destination port, payload). A length beyond the captured bytes means
/// snaplen cut the packet; the short payload is returned so the size check
/// downstream can report it instead of the packet silently vanishing.
fn udp_payload(udp: &[u8]) -> Option<(u16, &[u8])> {
    if udp.len() < 8 {
        return None;
    }
    let len = usize::from(be16(udp, 4));
    if len < 8 {
        return None;
    }
    Some((be16(udp, 2), &udp[8..len.min(udp.len())]))
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct FragKey {
    src: [u8; 4],
    dst: [u8; 4],
    id: u16,
}

/// One datagram being reassembled.
struct Partial {
    key: FragKey,
    data: Vec<u8>,
    /// Byte ranges received, unsorted; overlaps are allowed.
    ranges: Vec<(usize, usize)>,
    /// Payload length, known once the last fragment (MF = 0) arrives.
    total: Option<usize>,
}

impl Partial {
    fn is_complete(&self) -> bool {
        let Some(total) = self.total else {
            return false;
        };
        let mut ranges = self.ranges.clone();
        ranges.sort_unstable();
        let mut covered = 0;
        for (start, end) in ranges {
            if start > covered {
                return false;
            }
            covered = covered.max(end);
        }
        covered >= total
    }
}

/// IPv4 fragment reassembly keyed by (src, dst, id), with a fixed number of
/// buffers (oldest evicted first) so hostile captures cannot grow memory.
#[derive(Default)]
struct Reassembler {
    partials: VecDeque<Partial>,
}

impl Reassembler {
    /// Adds a fragment; returns the whole IP payload once it is complete.
    fn push(&mut self, key: FragKey, offset: usize, more: bool, frag: &[u8]) -> Option<Vec<u8>> {
        let end = offset + frag.len();
        if end > MAX_IPV4_PAYLOAD {
            return None;
        }
        let slot = self.slot(key);
        let partial = &mut self.partials[slot];
        if !more {
            if partial.total.is_some_and(|t| t != end) {
                self.partials.remove(slot);
                return None;
            }
            partial.total = Some(end);
        }
        if partial.ranges.len() >= MAX_FRAGMENTS {
            self.partials.remove(slot);
            return None;
        }
        if partial.data.len() < end {
            partial.data.resize(end, 0);
        }
        partial.data[offset..end].copy_from_slice(frag);
        partial.ranges.push((offset, end));
        if !partial.is_complete() {
            return None;
        }
        let mut done = self.partials.remove(slot)?;
        done.data.truncate(done.total.unwrap_or(0));
        Some(done.data)
    }

    /// Index of the buffer for `key`, creating (and evicting) as needed.
    fn slot(&mut self, key: FragKey) -> usize {
        if let Some(i) = self.partials.iter().position(|p| p.key == key) {
            return i;
        }
        if self.partials.len() >= MAX_PARTIALS {
            self.partials.pop_front();
        }
        self.partials.push_back(Partial {
            key,
            data: Vec::new(),
            ranges: Vec::new(),
            total: None,
        });
        self.partials.len() - 1
    }
}

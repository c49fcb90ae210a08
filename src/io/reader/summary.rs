//! The summary section of an intact file: schemas and channels to rebuild definitions lost
//! with a damaged chunk, and the chunk index to resume reading after a damaged record.

use std::collections::HashMap;
use std::io::{Read, Seek, SeekFrom};

use mcap::records::{Record, op};

use super::chunk::for_each_record;

/// The summary section of a file whose footer and summary are intact: its schemas and
/// channels, and where each chunk starts.
#[derive(Debug, Default)]
pub struct Summary {
    /// File offset of the summary section.
    pub start: u64,
    pub schemas: HashMap<u16, (mcap::records::SchemaHeader, Vec<u8>)>,
    pub channels: HashMap<u16, mcap::records::Channel>,
    pub chunks: Vec<mcap::records::ChunkIndex>,
    /// Chunk start offsets, ascending.
    pub chunk_offsets: Vec<u64>,
}

/// Footer record (opcode, length, summary start, summary offset start, CRC) + end magic.
const FOOTER_AND_MAGIC: u64 = 1 + 8 + 20 + 8;

/// Largest summary section read into memory.
const MAX_SUMMARY_BYTES: u64 = 256 << 20;

impl Summary {
    /// Reads and checks the footer and summary section of a `file_len`-byte file.
    pub fn read<R: Read + Seek>(src: &mut R, file_len: u64) -> Result<Summary, String> {
        if file_len < 8 + FOOTER_AND_MAGIC {
            return Err("too short for a footer".into());
        }
        let footer_at = file_len - FOOTER_AND_MAGIC;
        let mut tail = [0u8; FOOTER_AND_MAGIC as usize];
        src.seek(SeekFrom::Start(footer_at))
            .and_then(|_| src.read_exact(&mut tail))
            .map_err(|e| e.to_string())?;
        if tail[0] != op::FOOTER || tail[29..] != mcap::MAGIC[..] {
            return Err("no footer".into());
        }
        let u64_at = |k: usize| u64::from_le_bytes(tail[k..k + 8].try_into().unwrap_or_default());
        let (start, crc) = (
            u64_at(9),
            u32::from_le_bytes(tail[25..29].try_into().unwrap_or_default()),
        );
        if start < 8 || start >= footer_at || footer_at - start > MAX_SUMMARY_BYTES {
            return Err(format!("footer gives an impossible summary start {start}"));
        }
        let mut bytes = vec![0u8; (footer_at - start) as usize];
        src.seek(SeekFrom::Start(start))
            .and_then(|_| src.read_exact(&mut bytes))
            .map_err(|e| e.to_string())?;
        if crc != 0 {
            let mut hasher = crc32fast::Hasher::new();
            hasher.update(&bytes);
            hasher.update(&tail[..25]);
            if hasher.finalize() != crc {
                return Err("summary CRC mismatch".into());
            }
        }
        let mut summary = Summary {
            start,
            ..Default::default()
        };
        let mut unreadable = false;
        for_each_record(
            &bytes,
            |rec| {
                summary.add(rec);
                Ok(())
            },
            |_, _, _| unreadable = true,
        )
        .ok()
        .filter(|_| !unreadable)
        .ok_or_else(|| "unreadable summary record".to_string())?;
        summary.chunk_offsets = summary
            .chunks
            .iter()
            .map(|c| c.chunk_start_offset)
            .collect();
        summary.chunk_offsets.sort_unstable();
        summary.chunk_offsets.retain(|&o| o >= 8 && o < start);
        Ok(summary)
    }

    pub(super) fn add(&mut self, rec: &Record<'_>) {
        match rec {
            Record::Schema { header, data } => {
                self.schemas
                    .insert(header.id, (header.clone(), data.to_vec()));
            }
            Record::Channel(c) => {
                self.channels.insert(c.id, c.clone());
            }
            Record::ChunkIndex(c) => self.chunks.push(c.clone()),
            _ => {}
        }
    }

    pub(super) fn topic(&self, id: u16) -> Option<String> {
        self.channels.get(&id).map(|c| c.topic.clone())
    }
}

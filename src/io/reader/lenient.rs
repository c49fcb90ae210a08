//! What the reference readers still read where the mcap crate's parser refuses: a metadata
//! record with a repeated key (the last value wins, as Python's reader keeps it) and an
//! attachment whose CRC does not match (its contents are returned; the copy gets a CRC of its
//! own). Each comes with a note for the report.

use std::borrow::Cow;
use std::collections::BTreeMap;

use mcap::records::{AttachmentHeader, Metadata, Record, op};

pub fn parse(opcode: u8, data: &[u8]) -> Option<(Record<'_>, String)> {
    let mut c = Cursor(data);
    match opcode {
        op::METADATA => {
            let name = c.string()?;
            let map_len = usize::try_from(c.u32()?).ok()?;
            let mut map = Cursor(c.take(map_len)?);
            let (mut metadata, mut repeated) = (BTreeMap::new(), Vec::new());
            while !map.0.is_empty() {
                let (k, v) = (map.string()?, map.string()?);
                if let Some(old) = metadata.insert(k.clone(), v) {
                    repeated.push(format!("{k:?} (dropped value {old:?})"));
                }
            }
            (c.0.is_empty() && !repeated.is_empty()).then(|| {
                let note = format!(
                    "repeated keys in metadata {name:?}, the last value kept: {}",
                    repeated.join(", ")
                );
                (Record::Metadata(Metadata { name, metadata }), note)
            })
        }
        op::ATTACHMENT => {
            let (log_time, create_time) = (c.u64()?, c.u64()?);
            let (name, media_type) = (c.string()?, c.string()?);
            let len = usize::try_from(c.u64()?).ok()?;
            let body = c.take(len)?;
            let crc = c.u32()?;
            let calculated = crc32fast::hash(&data[..data.len() - c.0.len() - 4]);
            (c.0.is_empty() && crc != 0 && crc != calculated).then(|| {
                let note = format!(
                    "attachment {name:?}: CRC mismatch (saved {crc:#010x}, calculated {calculated:#010x}); copied as read"
                );
                let header = AttachmentHeader {
                    log_time,
                    create_time,
                    name,
                    media_type,
                };
                let rec = Record::Attachment {
                    header,
                    data: Cow::Borrowed(body),
                    crc: calculated,
                };
                (rec, note)
            })
        }
        _ => None,
    }
}

/// Little-endian fields off the front of a byte slice.
struct Cursor<'a>(&'a [u8]);

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let (head, rest) = (self.0.get(..n)?, self.0.get(n..)?);
        self.0 = rest;
        Some(head)
    }
    fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }
    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
    fn string(&mut self) -> Option<String> {
        let n = usize::try_from(self.u32()?).ok()?;
        String::from_utf8(self.take(n)?.to_vec()).ok()
    }
}

//! One record at a time: the length checks made before the mcap crate parses a record (so
//! no length field can ask for more than the record holds), and how a record is named in a
//! report.

use std::io::{Read, Seek, SeekFrom};

use mcap::records::{Record, op};

/// One field of a record's layout, as far as lengths go.
#[derive(Clone, Copy)]
pub(super) enum Field {
    Fixed(usize),
    /// u32 length + bytes (strings and schema data).
    Bytes32,
    /// u64 length + bytes (chunk records, attachment data).
    Bytes64,
    /// u32 byte length + entries of two u32-length strings.
    StringMap,
    /// Everything to the end (message data).
    Rest,
}

/// The fields of each record kind (MCAP specification), for [`check_lengths`].
pub(super) fn layout(opcode: u8) -> &'static [Field] {
    use Field::*;
    match opcode {
        op::HEADER => &[Bytes32, Bytes32],
        op::SCHEMA => &[Fixed(2), Bytes32, Bytes32, Bytes32],
        op::CHANNEL => &[Fixed(4), Bytes32, Bytes32, StringMap],
        op::MESSAGE => &[Fixed(22), Rest],
        op::CHUNK => &[Fixed(28), Bytes32, Bytes64],
        op::MESSAGE_INDEX => &[Fixed(2), Bytes32],
        op::CHUNK_INDEX => &[Fixed(32), Bytes32, Fixed(8), Bytes32, Fixed(16)],
        op::ATTACHMENT => &[Fixed(16), Bytes32, Bytes32, Bytes64, Fixed(4)],
        op::ATTACHMENT_INDEX => &[Fixed(40), Bytes32, Bytes32],
        op::STATISTICS => &[Fixed(42), Bytes32],
        op::METADATA => &[Bytes32, StringMap],
        op::METADATA_INDEX => &[Fixed(16), Bytes32],
        _ => &[Rest],
    }
}

/// Checks every length field of a record against the record's own size before the
/// mcap crate parses it: its parser allocates what a length field says first, so a
/// flipped bit in one would ask for gigabytes.
pub(super) fn check_lengths(opcode: u8, data: &[u8]) -> Result<(), String> {
    let mut at = 0usize;
    let take = |at: &mut usize, n: u64, what: &str| -> Result<(), String> {
        let left = (data.len() - *at) as u64;
        if n > left {
            return Err(format!(
                "{what} of {n} bytes at byte {} of the record, only {left} left",
                *at
            ));
        }
        *at += n as usize;
        Ok(())
    };
    let read_len = |at: &mut usize, width: usize| -> Result<u64, String> {
        let bytes = data
            .get(*at..*at + width)
            .ok_or_else(|| format!("record cut short at byte {}", *at))?;
        *at += width;
        let mut buf = [0u8; 8];
        buf[..width].copy_from_slice(bytes);
        Ok(u64::from_le_bytes(buf))
    };
    for field in layout(opcode) {
        match *field {
            Field::Fixed(n) => take(&mut at, n as u64, "fixed fields")?,
            Field::Bytes32 => {
                let n = read_len(&mut at, 4)?;
                take(&mut at, n, "a field")?;
            }
            Field::Bytes64 => {
                let n = read_len(&mut at, 8)?;
                take(&mut at, n, "a field")?;
            }
            Field::StringMap => {
                let n = read_len(&mut at, 4)?;
                let end = at;
                take(&mut at, n, "a map")?;
                let mut inner = end;
                while inner < at {
                    for _ in 0..2 {
                        let len = data
                            .get(inner..inner + 4)
                            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
                            .ok_or("map entry cut short")?;
                        inner = inner
                            .checked_add(4 + len)
                            .filter(|&e| e <= at)
                            .ok_or_else(|| format!("map entry of {len} bytes overruns its map"))?;
                    }
                }
            }
            Field::Rest => return Ok(()),
        }
    }
    Ok(())
}

/// `mcap::parse_record` after [`check_lengths`].
pub(super) fn parse_record(opcode: u8, data: &[u8]) -> Result<Record<'_>, String> {
    check_lengths(opcode, data)?;
    mcap::parse_record(opcode, data).map_err(|e| e.to_string())
}

/// The kind of record with `opcode`, for messages.
pub(super) fn record_kind(opcode: u8) -> String {
    let name = match opcode {
        op::HEADER => "header",
        op::FOOTER => "footer",
        op::SCHEMA => "schema",
        op::CHANNEL => "channel",
        op::MESSAGE => "message",
        op::CHUNK => "chunk",
        op::MESSAGE_INDEX => "message index",
        op::CHUNK_INDEX => "chunk index",
        op::ATTACHMENT => "attachment",
        op::ATTACHMENT_INDEX => "attachment index",
        op::STATISTICS => "statistics",
        op::METADATA => "metadata",
        op::METADATA_INDEX => "metadata index",
        op::SUMMARY_OFFSET => "summary offset",
        op::DATA_END => "data end",
        _ => "unknown record",
    };
    format!("{name} (opcode {opcode:#04x})")
}

/// The kind and declared length of the record at `offset`, read without trusting it.
pub(super) fn peek_record_kind<R: Read + Seek>(src: &mut R, offset: u64) -> String {
    let mut head = [0u8; 9];
    let read = src
        .seek(SeekFrom::Start(offset))
        .and_then(|_| src.read_exact(&mut head));
    match read {
        Ok(()) => format!(
            "{} declaring {} bytes",
            record_kind(head[0]),
            u64::from_le_bytes(head[1..9].try_into().unwrap_or_default())
        ),
        Err(_) => "record".into(),
    }
}

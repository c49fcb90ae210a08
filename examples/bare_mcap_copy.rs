//! Baseline for the pass-through benchmark: read an MCAP with the bare `mcap`
//! crate's streaming reader and rewrite every schema, channel, message,
//! attachment and metadata record with its writer, using the same chunking and
//! compression as `rangegan-mcap convert`. No error handling beyond `?`.
//!
//! `cargo run --release --example bare_mcap_copy -- IN.mcap OUT.mcap`

use std::io::Read;

use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (input, output) = (&args[1], &args[2]);
    let mut src = std::io::BufReader::with_capacity(1 << 20, std::fs::File::open(input)?);
    let out = std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(output)?);
    let mut w = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .compression_level(3)
        .chunk_size(Some(4 * 1024 * 1024))
        .create(out)?;
    let mut reader = LinearReader::new();
    while let Some(event) = reader.next_event() {
        match event? {
            LinearReadEvent::ReadRequest(n) => {
                let got = src.read(reader.insert(n))?;
                reader.notify_read(got);
            }
            LinearReadEvent::Record { opcode, data } => match mcap::parse_record(opcode, data)? {
                Record::Schema { header, data } => {
                    w.add_schema_with_id(header.id, &header.name, &header.encoding, &data)?;
                }
                Record::Channel(c) => {
                    w.add_channel_with_id(
                        c.id,
                        c.schema_id,
                        &c.topic,
                        &c.message_encoding,
                        &c.metadata,
                    )?;
                }
                Record::Message { header, data } => w.write_to_known_channel(&header, &data)?,
                Record::Attachment { header, data, .. } => w.attach(&mcap::Attachment {
                    log_time: header.log_time,
                    create_time: header.create_time,
                    name: header.name,
                    media_type: header.media_type,
                    data,
                })?,
                Record::Metadata(m) => w.write_metadata(&m)?,
                _ => {}
            },
        }
    }
    w.finish()?;
    Ok(())
}

//! The schemas and channels a record stream has defined so far, so that a consumer of
//! [`super::read_records`] can tell what a message is: its topic, schema and, for point
//! clouds, the wire format [`super::decode_cloud`] needs.

use std::collections::HashMap;

use mcap::records::Record;

use super::CloudFormat;

/// One channel as its Channel record (and its schema) defined it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ChannelEntry {
    pub topic: String,
    /// Schema name ("" for schemaless channels).
    pub schema: String,
    pub schema_encoding: String,
    pub message_encoding: String,
    /// The point-cloud format, when the channel carries a point-cloud type we decode.
    pub cloud: Option<CloudFormat>,
}

/// Schemas and channels by id, learnt from the records as they stream past.
#[derive(Debug, Default)]
pub struct ChannelTable {
    schemas: HashMap<u16, (String, String)>,
    channels: HashMap<u16, ChannelEntry>,
}

impl ChannelTable {
    /// Learns from a Schema or Channel record (other records are ignored); returns the
    /// channel's id and entry when `record` defines one.
    pub fn observe(&mut self, record: &Record<'_>) -> Option<(u16, &ChannelEntry)> {
        match record {
            Record::Schema { header, .. } => {
                self.schemas
                    .insert(header.id, (header.name.clone(), header.encoding.clone()));
                None
            }
            Record::Channel(c) => {
                let (schema, schema_encoding) =
                    self.schemas.get(&c.schema_id).cloned().unwrap_or_default();
                let entry = ChannelEntry {
                    topic: c.topic.clone(),
                    cloud: CloudFormat::detect(&c.message_encoding, &schema),
                    schema,
                    schema_encoding,
                    message_encoding: c.message_encoding.clone(),
                };
                self.channels.insert(c.id, entry);
                self.channels.get(&c.id).map(|e| (c.id, e))
            }
            _ => None,
        }
    }

    /// The channel a message was written on.
    pub fn get(&self, channel_id: u16) -> Option<&ChannelEntry> {
        self.channels.get(&channel_id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::encoders::{Kind, schema};
    use crate::io::{Family, McapOutput, OnError, read_records};

    #[test]
    fn channels_know_their_schema_and_point_cloud_format() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.mcap");
        let mut out = McapOutput::create(&path, false).unwrap();
        let cloud = out
            .own_channel("/points", Family::Ros2, Kind::Cloud)
            .unwrap();
        let image = out
            .own_channel("/image", Family::Ros2, Kind::Image)
            .unwrap();
        out.write_own(cloud, 1, 1, &[0u8; 4]).unwrap();
        out.write_own(image, 2, 2, &[0u8; 4]).unwrap();
        out.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let mut table = ChannelTable::default();
        let mut defined = Vec::new();
        let mut messages = Vec::new();
        let visit = |record: &Record<'_>| {
            if let Some((id, e)) = table.observe(record) {
                defined.push((id, e.topic.clone()));
            }
            if let Record::Message { header, .. } = record {
                messages.push(table.get(header.channel_id).unwrap().clone());
            }
            Ok(())
        };
        read_records(
            std::io::Cursor::new(&bytes[..]),
            None,
            OnError::Fail,
            visit,
            |_| {},
        )
        .unwrap();
        assert!(defined.contains(&(cloud, "/points".to_string())));
        let (p, i) = (&messages[0], &messages[1]);
        assert_eq!(p.topic, "/points");
        assert_eq!(
            p.cloud,
            Some(CloudFormat::detect("cdr", &p.schema).unwrap())
        );
        assert_eq!(p.schema, schema(Family::Ros2, Kind::Cloud).name);
        assert_eq!(
            (p.message_encoding.as_str(), p.schema_encoding.as_str()),
            ("cdr", "ros2msg")
        );
        assert_eq!((i.topic.as_str(), i.cloud), ("/image", None));
        assert!(table.get(999).is_none());
    }
}

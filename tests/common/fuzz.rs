//! What the fuzzer runs on every input, shared by `examples/fuzz_reader.rs` and the
//! regression test over `tests/fuzz_regressions/`: the streaming reader in both error
//! modes, every point-cloud message through the decoders, sensor estimation and
//! projection. Any panic is a bug; errors are expected.

use std::io::Cursor;

use rangegan_mcap::io::{ChannelTable, OnError, decode_cloud, read_records};
use rangegan_mcap::lidar::{SensorProfile, Strategy, estimate_profile, project};

/// Runs `bytes` through the reader and the point-cloud path; returns the messages read.
pub fn exercise(bytes: &[u8]) -> u64 {
    let mut messages = 0;
    for on_error in [OnError::Skip, OnError::Fail] {
        let mut table = ChannelTable::default();
        let _ = read_records(
            Cursor::new(bytes),
            Some(bytes.len() as u64),
            on_error,
            |record| {
                table.observe(record);
                if let mcap::records::Record::Message { header, data } = record {
                    messages += 1;
                    if let Some(format) = table.get(header.channel_id).and_then(|c| c.cloud) {
                        cloud_path(format, data);
                    }
                }
                Ok(())
            },
            |_| {},
        );
    }
    messages
}

/// Decoding, estimation and projection of one message, as `convert` does them.
pub fn cloud_path(format: rangegan_mcap::io::CloudFormat, data: &[u8]) {
    let Ok(cloud) = decode_cloud(format, data) else {
        return;
    };
    let profile = estimate_profile(std::slice::from_ref(&cloud.scan))
        .map(|e| e.profile)
        .unwrap_or_else(|_| SensorProfile::kitti_hdl64e());
    for strategy in [Strategy::Auto, Strategy::Spherical, Strategy::RingField] {
        if let Ok(image) = project(&cloud.scan, &profile, strategy) {
            // A silent corruption is a bug as much as a panic: no pixel may hold an
            // infinite or absurd range, whatever the message held.
            let max = rangegan_mcap::lidar::scan::MAX_RETURN_RANGE_M;
            if let Some(r) = image.range_m.iter().find(|r| !(0.0..=max).contains(*r)) {
                panic!("a range of {r} m reached a pixel ({strategy:?})");
            }
        }
    }
}

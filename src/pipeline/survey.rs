//! The first pass of a conversion that decodes: each converted topic's profile, row strategy
//! and coverage are fixed on its first scans in file order, and every topic's drops are
//! counted ([`DropCensus`]), so each scan's `raydrop_prob` can draw on the recording's other
//! scans. Damaged records are passed over here; the main pass reports them.

use std::collections::HashMap;
use std::io::{Read, Seek};

use mcap::records::Record;
use rayon::prelude::*;

use super::{Converter, ScanProcessor};
use crate::io::{ChannelTable, DecodedCloud, OnError, decode_cloud, read_records};
use crate::lidar::drop_census::DropCensus;
use crate::lidar::{SensorProfile, Strategy, project};

/// Scans decoded before they are projected together: the projections run in parallel, and
/// the pass holds at most this many decoded clouds.
const PROJECT_TOGETHER: usize = 16;

/// A scan of the first pass waiting for its projection: its topic, profile and strategy
/// (fixed in file order) and the decoded cloud.
type Waiting = (String, SensorProfile, Strategy, DecodedCloud);

/// Runs the first pass over `src` and leaves its counts in `processor`.
pub(super) fn survey(
    processor: &mut ScanProcessor<'_, '_>,
    src: &mut (impl Read + Seek),
    file_len: Option<u64>,
) {
    if processor.opts.prior.is_none() {
        return;
    }
    let mut table = ChannelTable::default();
    let mut census: HashMap<String, DropCensus> = HashMap::new();
    let mut waiting: Vec<Waiting> = Vec::new();
    let opts = processor.opts;
    let proc_ref = &*processor;
    let visit = |record: &Record<'_>| {
        table.observe(record);
        let Record::Message { header, data } = record else {
            return Ok(());
        };
        let Some(channel) = table.get(header.channel_id) else {
            return Ok(());
        };
        let Some(format) = Converter::converted(opts, channel) else {
            return Ok(());
        };
        let Ok(cloud) = decode_cloud(format, data) else {
            return Ok(());
        };
        let topic = &channel.topic;
        let Ok((profile, strategy)) = proc_ref.profile_for(topic, header.log_time, &cloud) else {
            return Ok(());
        };
        waiting.push((topic.clone(), profile, strategy, cloud));
        if waiting.len() >= PROJECT_TOGETHER {
            count_drops(&mut waiting, &mut census);
        }
        Ok(())
    };
    // A file the main pass cannot read either: it says why.
    let _ = read_records(&mut *src, file_len, OnError::Skip, visit, |_| {});
    count_drops(&mut waiting, &mut census);
    processor.census = census;
}

/// Projects the `waiting` scans in parallel and adds them to their topics' counts in file
/// order (a topic's first scan sets its grid).
fn count_drops(waiting: &mut Vec<Waiting>, census: &mut HashMap<String, DropCensus>) {
    let images: Vec<_> = (waiting.par_iter())
        .map(|(_, profile, strategy, cloud)| project(&cloud.scan, profile, *strategy).ok())
        .collect();
    for ((topic, ..), image) in waiting.drain(..).zip(images) {
        if let Some(image) = image {
            (census.entry(topic))
                .or_insert_with(|| DropCensus::new(image.height, image.width))
                .add(&image);
        }
    }
}

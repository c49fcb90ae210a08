//! The first pass of a conversion that decodes: each converted topic's profile, row strategy
//! and coverage are fixed on its first scans in file order, and every topic's drops are
//! counted ([`DropCensus`]), so each scan's `raydrop_prob` can draw on the recording's other
//! scans. On a topic no model covers, the prior-free hole fill is checked on its first scans
//! ([`FillCheck`]). Damaged records are passed over here; the main pass reports them.

use std::collections::HashMap;
use std::io::{Read, Seek};

use mcap::records::Record;
use rayon::prelude::*;

use super::{Converter, ScanProcessor};
use crate::decode::prior_free::FillCheck;
use crate::decode::scan_seed;
use crate::io::{ChannelTable, CloudFormat, DecodedCloud, OnError, decode_cloud, read_records};
use crate::lidar::drop_census::DropCensus;
use crate::lidar::{RangeImage, SensorProfile, Strategy, project};

/// Scans read before they are decoded and projected together: decoding and projecting run
/// in parallel, and the pass holds at most this many scans.
const SURVEY_TOGETHER: usize = 16;

/// A point-cloud message of the first pass waiting to be counted: its topic, log time,
/// encoding and bytes.
type Waiting = (String, u64, CloudFormat, Vec<u8>);

/// Runs the first pass over `src` and leaves its counts in `processor`.
pub(super) fn survey(
    processor: &mut ScanProcessor<'_, '_>,
    src: &mut (impl Read + Seek),
    file_len: Option<u64>,
) {
    if processor.opts.prior.is_none() && !processor.opts.check_every_fill {
        return;
    }
    let mut table = ChannelTable::default();
    let mut census: HashMap<String, DropCensus> = HashMap::new();
    let mut checks: HashMap<String, FillCheck> = HashMap::new();
    let mut waiting: Vec<Waiting> = Vec::new();
    let opts = processor.opts;
    // The recording's own drop counts serve the GAN's ray drop; without it the first pass
    // only checks the fill.
    let census_wanted = opts.prior.is_some();
    let mut queued: HashMap<String, usize> = HashMap::new();
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
        if !census_wanted {
            // Only the fill check, on each topic's first scans: the others are not decoded.
            let queued = queued.entry(channel.topic.clone()).or_insert(0usize);
            if *queued >= FillCheck::SCANS {
                return Ok(());
            }
            *queued += 1;
        }
        waiting.push((
            channel.topic.clone(),
            header.log_time,
            format,
            data.to_vec(),
        ));
        if waiting.len() >= SURVEY_TOGETHER {
            count_drops(proc_ref, &mut waiting, &mut census, &mut checks);
        }
        Ok(())
    };
    // A file the main pass cannot read either: it says why.
    let _ = read_records(&mut *src, file_len, OnError::Skip, visit, |_| {});
    count_drops(proc_ref, &mut waiting, &mut census, &mut checks);
    processor.census = census;
    processor.fill_checks = checks;
}

/// Counts the drops of the `waiting` scans: decoded in parallel, each topic's profile fixed
/// in file order, projected in parallel, and added to their topics' counts in file order (a
/// topic's first scan sets its grid); and checks the prior-free hole fill on the first
/// scans of each topic no model covers, or of every topic where the options say (in
/// parallel, merged in file order).
fn count_drops(
    processor: &ScanProcessor<'_, '_>,
    waiting: &mut Vec<Waiting>,
    census: &mut HashMap<String, DropCensus>,
    checks: &mut HashMap<String, FillCheck>,
) {
    let clouds: Vec<Option<DecodedCloud>> = (waiting.par_iter())
        .map(|(_, _, format, data)| decode_cloud(*format, data).ok())
        .collect();
    let projections: Vec<Option<(SensorProfile, Strategy)>> = (waiting.iter().zip(&clouds))
        .map(|((topic, log_time, ..), cloud)| {
            let cloud = cloud.as_ref()?;
            processor.profile_for(topic, *log_time, cloud).ok()
        })
        .collect();
    let images: Vec<Option<RangeImage>> = (clouds.par_iter().zip(&projections))
        .map(|(cloud, projection)| {
            let (cloud, (profile, strategy)) = (cloud.as_ref()?, projection.as_ref()?);
            project(&cloud.scan, profile, *strategy).ok()
        })
        .collect();
    let mut wanted: HashMap<&str, usize> = HashMap::new();
    let to_check: Vec<bool> = (waiting.iter().zip(&images))
        .map(|((topic, ..), image)| {
            let checked = processor.opts.check_every_fill || !processor.covered(topic);
            if image.is_none() || !checked {
                return false;
            }
            let done = checks.get(topic.as_str()).map_or(0, FillCheck::scans);
            let n = wanted.entry(topic).or_insert(done);
            *n += 1;
            *n <= FillCheck::SCANS
        })
        .collect();
    let checked: Vec<Option<FillCheck>> = (waiting.par_iter().zip(&images).zip(&to_check))
        .map(|(((topic, log_time, ..), image), &check)| {
            let image = image.as_ref().filter(|_| check)?;
            Some(FillCheck::on(image, scan_seed(topic, *log_time)))
        })
        .collect();
    for (((topic, ..), image), check) in waiting.drain(..).zip(images).zip(checked) {
        if let Some(check) = check {
            checks.entry(topic.clone()).or_default().merge(&check);
        }
        if let Some(image) = image.filter(|_| processor.opts.prior.is_some()) {
            (census.entry(topic))
                .or_insert_with(|| DropCensus::new(image.height, image.width))
                .add(&image);
        }
    }
}

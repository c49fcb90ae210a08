//! One pass over a recording: every input record is copied to the output, every
//! point-cloud message is decoded and projected, and per-scan stages add new
//! channels under `<topic>/rangegan/`. Scans are processed in parallel (rayon) in
//! bounded batches and written back in input order, so the output is the same
//! whatever the thread count and memory does not grow with the file. A thread of its own
//! processes the batches while the reading side copies the next batch's records and writes
//! the previous batch's outputs after them.
//!
//! A topic's scans may form chains ([`ConvertOptions::chain_stride`]): scan k continues
//! from what scan k - stride left in its chain's [`ChainState`] (the decoder's tuned weights),
//! so each chain runs in input order and chains run in parallel. A stage may hand its chain's
//! state on before its scan is done ([`Staged::Later`]); the rest of that scan then runs
//! beside the chain's next scan. The chains follow from the scans' order alone, never from the
//! threads.

use std::collections::{BTreeMap, HashMap};
use std::io::{Read, Seek};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, mpsc};

use mcap::records::Record;

use crate::decode::prior_free::FillCheck;
use crate::error::Location;
use crate::io::encoders::Kind;
use crate::io::{
    ChannelEntry, ChannelTable, CloudFormat, DecodedCloud, Family, McapOutput, OnError, ReadReport,
    decode_cloud, read_records,
};
use crate::lidar::drop_census::DropCensus;
use crate::lidar::{RangeImage, SensorProfile, Strategy, estimate_profile, project};
use crate::model::generator::Generator;

mod spatial;
mod stages;
mod survey;

pub use spatial::{SpatialOutputs, SpatialStage};
pub use stages::{DecodeOutputs, DecodeStage, range_stage};

/// Which sensor grid a topic's scans are projected onto.
#[derive(Debug, Clone)]
pub enum SensorChoice {
    /// Estimated from each topic's first scan.
    Auto,
    Fixed(SensorProfile),
}

/// What to convert and how.
#[derive(Debug, Clone)]
pub struct ConvertOptions {
    /// Topics to process; `None` = every point-cloud topic.
    pub topics: Option<Vec<String>>,
    pub sensor: SensorChoice,
    /// Columns of the range image; `None` = the profile's own.
    pub columns: Option<usize>,
    pub strategy: Strategy,
    pub on_error: OnError,
    /// Scans decoded in parallel per batch.
    pub batch_scans: usize,
    /// Entries of the `rangegan` metadata record written to the output.
    pub metadata: BTreeMap<String, String>,
    /// Keep no output when anything was skipped (the run then exits non-zero).
    pub strict: bool,
    /// Counts scans as their stages finish (before their batch is written), for progress.
    pub scans_processed: Option<Arc<AtomicU64>>,
    /// Whether and where scans go through the decoding model (`None`: nothing is decoded,
    /// no coverage is checked). When decoding, a first pass over the file counts every
    /// converted topic's drops ([`survey`]): the recording's own rates.
    pub prior: Option<PriorUse>,
    /// The sensor the decoding model was trained for: a topic's coverage is judged against
    /// it.
    pub model_sensor: SensorProfile,
    /// Scans of a topic in chains: scan k continues from scan k - stride (0: each scan alone).
    pub chain_stride: usize,
    /// Check the prior-free hole fill on every converted topic's first scans in the first
    /// pass ([`survey`]), not only where no model covers the sensor: a decoder whose `depth`
    /// completes holes without its prior (the spatial model's) then reuses one check per
    /// topic instead of probing every scan.
    pub check_every_fill: bool,
}

/// Where the decoding stage uses its model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PriorUse {
    /// On topics whose sensor the model covers ([`crate::decode::fit::ModelFit::covers`]);
    /// the others get prior-free channels.
    WhereCovered,
    /// On every topic (`--model` given): a warning says where the model does not cover.
    Always,
    /// On no topic (`--prior-free`): every topic gets prior-free channels.
    Never,
}

/// Scans per parallel batch. Fixed rather than tied to the thread count: outputs of a batch are
/// written after its last input record, so the batch size decides how copied and new records
/// interleave, and the output file must be the same bytes whatever the thread count.
pub const DEFAULT_BATCH_SCANS: usize = 16;

/// Chains per topic: one per core of the 2-core machines the tool is sized for. Fixed rather
/// than tied to the thread count, since a scan's result depends on its chain.
pub const DEFAULT_CHAIN_STRIDE: usize = 2;

/// What a chain of scans carries from one scan to the next: the pivotal-tuned weights the last
/// scan handed on.
pub type ChainState = Mutex<Option<Generator>>;

/// A chain: its topic and number within the topic.
type ChainKey = (String, usize);

impl Default for ConvertOptions {
    fn default() -> Self {
        ConvertOptions {
            topics: None,
            sensor: SensorChoice::Auto,
            columns: None,
            strategy: Strategy::Auto,
            on_error: OnError::Fail,
            batch_scans: DEFAULT_BATCH_SCANS,
            metadata: BTreeMap::new(),
            strict: false,
            scans_processed: None,
            prior: None,
            model_sensor: crate::model::config::default_sensor(),
            chain_stride: DEFAULT_CHAIN_STRIDE,
            check_every_fill: false,
        }
    }
}

/// One scan handed to the per-scan stages.
pub struct ScanInput<'a> {
    pub topic: &'a str,
    pub log_time: u64,
    pub family: Family,
    pub cloud: &'a DecodedCloud,
    pub image: &'a RangeImage,
    /// Whether the scan goes through the decoding model: it covers the topic's sensor, or a
    /// model was named (true where nothing checks).
    pub covered: bool,
    /// The recording's own drop counts on this topic's grid, where the first pass made them.
    pub census: Option<&'a DropCensus>,
    /// The check of the prior-free hole fill on the topic's first scans, where the first
    /// pass made it (topics no model covers, or every topic with
    /// [`ConvertOptions::check_every_fill`]).
    pub fill_check: Option<&'a FillCheck>,
    /// The scan's chain, when scans are chained; its scans reach the stages in input order.
    pub chain: Option<&'a ChainState>,
}

/// One message a stage adds, on channel `<topic>/rangegan/<suffix>`.
pub struct StageOutput {
    pub suffix: String,
    pub kind: Kind,
    pub data: Vec<u8>,
}

/// What a stage gives for one scan.
pub enum Staged<'s> {
    Done(Vec<StageOutput>),
    /// The part that the scan's chain waits for is done and its state handed on; this makes
    /// the outputs, beside the chain's next scan.
    Later(Later<'s>),
}

/// The rest of a stage's work on one scan ([`Staged::Later`]).
pub type Later<'s> = Box<dyn FnOnce() -> anyhow::Result<Vec<StageOutput>> + Send + 's>;

/// A per-scan stage: pure in its inputs, so results do not depend on threads.
pub type Stage<'s> = dyn Fn(&ScanInput<'_>) -> anyhow::Result<Staged<'s>> + Sync + 's;

/// Per-topic results for the summary.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct TopicReport {
    pub format: Option<CloudFormat>,
    pub scans: u64,
    /// Messages that could not be decoded or projected (copied through unchanged).
    pub malformed: u64,
    /// Scans for which an output stage failed (e.g. nothing to auto-decode); their other
    /// channels were written.
    pub stage_failures: u64,
    pub sensor: Option<String>,
    pub strategy: Option<String>,
    pub rows: usize,
    pub columns: usize,
    /// Mean fraction of a scan's returns that kept a pixel.
    pub kept_fraction: f64,
}

/// A warning about one message; the message itself was copied unchanged.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Warning {
    pub topic: String,
    pub log_time_nanos: u64,
    pub message: String,
}

/// What a conversion did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ConvertReport {
    pub read: ReadReport,
    pub records_in: RecordCounts,
    pub copied: crate::io::writer::CopyCounts,
    pub outputs_written: u64,
    pub topics: BTreeMap<String, TopicReport>,
    pub warnings: Vec<Warning>,
    /// Topics whose sensor is far from the decoding model's (their decoded channels are rough).
    pub model_fit: Vec<Warning>,
}

impl ConvertReport {
    /// Whether any input was skipped, unreadable or not converted: `--strict` fails then.
    pub fn skipped_anything(&self) -> bool {
        self.read.damaged()
            || self.copied.orphan_messages > 0
            || self
                .topics
                .values()
                .any(|t| t.malformed > 0 || t.stage_failures > 0)
    }
}

/// Counts of input records by kind (the ones a copy must preserve).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct RecordCounts {
    pub schemas: u64,
    pub channels: u64,
    pub messages: u64,
    pub attachments: u64,
    pub metadata: u64,
}

/// A point-cloud message waiting for its batch (the message itself is already
/// copied; its outputs follow when the batch is processed).
struct Pending {
    topic: String,
    /// The scan's chain within its topic (with chains).
    chain: Option<usize>,
    format: CloudFormat,
    log_time: u64,
    publish_time: u64,
    data: Vec<u8>,
}

/// The per-scan work, shared by the worker threads.
/// What decides a scan's row strategy: its organisation (and shape) and whether it has a
/// ring field.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
struct LayoutKey {
    organized: Option<(usize, usize)>,
    ring: bool,
}

impl LayoutKey {
    fn of(scan: &crate::lidar::Scan) -> Self {
        LayoutKey {
            organized: scan.is_organized().then_some((scan.height, scan.width)),
            ring: scan.ring.is_some(),
        }
    }
}

struct ScanProcessor<'a, 's> {
    opts: &'a ConvertOptions,
    stages: &'a [&'a Stage<'s>],
    /// The profile and strategy of each topic's layouts.
    profiles: Mutex<HashMap<(String, LayoutKey), (SensorProfile, Strategy)>>,
    file: std::path::PathBuf,
    fit_warnings: Mutex<Vec<Warning>>,
    /// Per topic: whether the decoding model covers its sensor (see [`PriorUse`]).
    coverage: Mutex<HashMap<String, bool>>,
    /// Per topic: the recording's own drop counts, from the first pass ([`survey`]).
    census: HashMap<String, DropCensus>,
    /// Per topic no model covers: the check of the prior-free hole fill, from the first pass.
    fill_checks: HashMap<String, FillCheck>,
}

/// A processed scan: the stages' outputs, the kept fraction, the profile and projection used,
/// the errors of stages that failed (the other stages' channels are still written) and the
/// decoder's notes on the cloud (see [`DecodedCloud::notes`]).
type Processed = (
    Vec<StageOutput>,
    f64,
    (SensorProfile, Strategy),
    Vec<String>,
    Vec<String>,
);

/// A scan whose stages have run up to what its chain waits for: each stage's result, in order.
struct Begun<'s> {
    staged: Vec<Result<Staged<'s>, String>>,
    kept: f64,
    projection: (SensorProfile, Strategy),
    notes: Vec<String>,
}

impl Begun<'_> {
    /// Runs what the stages left for later, and collects their outputs in stage order.
    fn complete(self) -> Processed {
        let (mut outputs, mut failed) = (Vec::new(), Vec::new());
        for staged in self.staged {
            let result = staged.and_then(|s| match s {
                Staged::Done(o) => Ok(o),
                Staged::Later(later) => later().map_err(|e| format!("{e:#}")),
            });
            match result {
                Ok(o) => outputs.extend(o),
                Err(e) => failed.push(e),
            }
        }
        (outputs, self.kept, self.projection, failed, self.notes)
    }
}

impl<'s> ScanProcessor<'_, 's> {
    /// The profile and strategy for `topic`. The profile is fixed by the topic's first scan;
    /// the strategy by the first scan of each layout (see [`LayoutKey`]), so a topic whose
    /// clouds turn from organized to unorganized projects each kind its own way. The model's
    /// coverage of the topic is settled on the way ([`Self::check_coverage`]).
    fn profile_for(
        &self,
        topic: &str,
        log_time: u64,
        cloud: &DecodedCloud,
    ) -> Result<(SensorProfile, Strategy), String> {
        let (profile, strategy) = self.layout_profile(topic, cloud)?;
        self.check_coverage(topic, log_time, &cloud.scan, &profile);
        Ok((profile, strategy))
    }

    /// [`Self::profile_for`] without the coverage.
    fn layout_profile(
        &self,
        topic: &str,
        cloud: &DecodedCloud,
    ) -> Result<(SensorProfile, Strategy), String> {
        let mut map = self.profiles.lock().unwrap_or_else(|e| e.into_inner());
        let key = (topic.to_string(), LayoutKey::of(&cloud.scan));
        if let Some(found) = map.get(&key) {
            return Ok(found.clone());
        }
        let first = map.iter().find(|((t, _), _)| t == topic);
        if let Some((_, (profile, _))) = first {
            let profile = profile.clone();
            let strategy = self.strategy(&cloud.scan, &profile);
            map.insert(key, (profile.clone(), strategy));
            return Ok((profile, strategy));
        }
        let profile = match &self.opts.sensor {
            SensorChoice::Fixed(p) => p.clone(),
            SensorChoice::Auto => {
                estimate_profile(std::slice::from_ref(&cloud.scan))
                    .map_err(|e| e.to_string())?
                    .profile
            }
        };
        let profile = match self.opts.columns {
            Some(c) => profile.with_columns(c),
            None => profile,
        };
        let strategy = self.strategy(&cloud.scan, &profile);
        map.insert(key, (profile.clone(), strategy));
        Ok((profile, strategy))
    }

    /// Decides, on the first scan of `topic` with returns, whether the decoding model covers
    /// its sensor, and says so where it does not (see [`PriorUse`]).
    fn check_coverage(
        &self,
        topic: &str,
        log_time: u64,
        scan: &crate::lidar::Scan,
        profile: &SensorProfile,
    ) {
        let Some(prior) = self.opts.prior else {
            return;
        };
        let mut coverage = self.coverage.lock().unwrap_or_else(|e| e.into_inner());
        if coverage.contains_key(topic) {
            return;
        }
        let Some(fit) = crate::decode::fit::model_fit(scan, profile, &self.opts.model_sensor)
        else {
            return;
        };
        coverage.insert(topic.to_string(), fit.covers());
        let sensor = format!("{}, {} beams", profile.name, profile.beams());
        let message = match prior {
            PriorUse::Always => fit.warning(&sensor),
            PriorUse::WhereCovered => (!fit.covers()).then(|| fit.prior_free_note(&sensor)),
            PriorUse::Never => None,
        };
        if let Some(w) = message {
            let loc = Location::message(&self.file, topic, log_time);
            let mut warnings = self.fit_warnings.lock().unwrap_or_else(|e| e.into_inner());
            warnings.push(Warning {
                topic: topic.to_string(),
                log_time_nanos: log_time,
                message: format!("{loc}: {w}"),
            });
        }
    }

    /// Fixes the profile (and coverage) of each topic of `batch` not seen before on its first
    /// scan in file order, before the batch's scans run in parallel: otherwise whichever scan
    /// a thread reached first would choose, and two runs could project on different grids.
    fn fix_profiles(&self, batch: &[Pending]) {
        for p in batch {
            let known = {
                let map = self.profiles.lock().unwrap_or_else(|e| e.into_inner());
                map.keys().any(|(t, _)| *t == p.topic)
            };
            if known && !self.coverage_pending(&p.topic) {
                continue;
            }
            if let Ok(cloud) = decode_cloud(p.format, &p.data) {
                let _ = self.profile_for(&p.topic, p.log_time, &cloud);
            }
        }
    }

    /// Whether `topic`'s coverage is still to be decided (decoding, and no scan with returns
    /// seen yet).
    fn coverage_pending(&self, topic: &str) -> bool {
        let coverage = self.coverage.lock().unwrap_or_else(|e| e.into_inner());
        self.opts.prior.is_some() && !coverage.contains_key(topic)
    }

    /// Whether `topic`'s scans go through the model: always with [`PriorUse::Always`], never
    /// with [`PriorUse::Never`], else where it covers the sensor (true until a scan with
    /// returns says).
    fn covered(&self, topic: &str) -> bool {
        match self.opts.prior {
            Some(PriorUse::Always) => return true,
            Some(PriorUse::Never) => return false,
            _ => {}
        }
        let coverage = self.coverage.lock().unwrap_or_else(|e| e.into_inner());
        coverage.get(topic).copied().unwrap_or(true)
    }

    /// The row strategy for `scan`: `--projection`, or else chosen from the data.
    fn strategy(&self, scan: &crate::lidar::Scan, profile: &SensorProfile) -> Strategy {
        match self.opts.strategy {
            Strategy::Auto => crate::lidar::projection::choose_strategy(scan, profile),
            s => s,
        }
    }

    /// Runs the stages on scan `p` up to what its chain waits for ([`Begun::complete`] does
    /// the rest).
    fn begin(&self, p: &Pending, chain: Option<&ChainState>) -> Result<Begun<'s>, String> {
        let cloud = decode_cloud(p.format, &p.data).map_err(|e| e.to_string())?;
        let (profile, strategy) = self.profile_for(&p.topic, p.log_time, &cloud)?;
        let image = project(&cloud.scan, &profile, strategy).map_err(|e| e.to_string())?;
        let returns = cloud.scan.returns().max(1);
        let kept = image.valid_count() as f64 / returns as f64;
        let input = ScanInput {
            topic: &p.topic,
            log_time: p.log_time,
            family: p.format.family(),
            cloud: &cloud,
            image: &image,
            covered: self.covered(&p.topic),
            census: self.census.get(&p.topic),
            fill_check: self.fill_checks.get(&p.topic),
            chain,
        };
        // One failing stage (e.g. a scan with nothing to decode) does not cost the others.
        let staged = (self.stages.iter())
            .map(|stage| stage(&input).map_err(|e| format!("{e:#}")))
            .collect();
        if let Some(counter) = &self.opts.scans_processed {
            counter.fetch_add(1, Ordering::Relaxed);
        }
        Ok(Begun {
            staged,
            kept,
            projection: (profile, strategy),
            notes: cloud.notes.clone(),
        })
    }
}

/// A batch of scans and what processing them gave, in the batch's order.
type BatchResults = (Vec<Pending>, Vec<Result<Processed, String>>);

struct Converter<'a> {
    out: McapOutput,
    opts: &'a ConvertOptions,
    file: std::path::PathBuf,
    table: ChannelTable,
    batch: Vec<Pending>,
    /// Scans seen per converted topic (they number the chains).
    topic_scans: HashMap<String, usize>,
    /// Full batches to the thread that processes them ([`process_batches`]), and back; the
    /// sender is dropped when reading ends, which ends that thread.
    to_process: Option<mpsc::Sender<Vec<Pending>>>,
    processed: mpsc::Receiver<BatchResults>,
    /// Batches handed over whose outputs are not written yet.
    in_flight: usize,
    scans_done: u64,
    report: ConvertReport,
}

impl Converter<'_> {
    /// The point-cloud format of a channel whose scans are converted (`--topic` selects).
    fn converted(opts: &ConvertOptions, channel: &ChannelEntry) -> Option<CloudFormat> {
        let selected = opts
            .topics
            .as_ref()
            .is_none_or(|t| t.contains(&channel.topic));
        channel.cloud.filter(|_| selected)
    }

    fn visit(&mut self, record: &Record<'_>) -> anyhow::Result<()> {
        if let Some((_, channel)) = self.table.observe(record)
            && let Some(format) = Self::converted(self.opts, channel)
        {
            let topic = self.report.topics.entry(channel.topic.clone());
            topic.or_default().format = Some(format);
        }
        let counts = &mut self.report.records_in;
        match record {
            Record::Schema { .. } => counts.schemas += 1,
            Record::Channel(_) => counts.channels += 1,
            Record::Message { .. } => counts.messages += 1,
            Record::Attachment { .. } => counts.attachments += 1,
            Record::Metadata(_) => counts.metadata += 1,
            _ => {}
        }
        // Copy first: the input record reaches the output whatever happens to its scan.
        self.out.copy_record(record)?;
        if let Record::Message { header, data } = record
            && let Some(channel) = self.table.get(header.channel_id)
            && let Some(format) = Self::converted(self.opts, channel)
        {
            let index = self.topic_scans.entry(channel.topic.clone()).or_default();
            let stride = self.opts.chain_stride;
            let chain = (stride > 0).then(|| *index % stride);
            *index += 1;
            self.batch.push(Pending {
                topic: channel.topic.clone(),
                chain,
                format,
                log_time: header.log_time,
                publish_time: header.publish_time,
                data: data.to_vec(),
            });
            if self.batch.len() >= self.opts.batch_scans.max(1) {
                self.hand_over()?;
            }
        }
        Ok(())
    }

    /// Hands the batch read so far to the processing thread and writes the outputs of the
    /// batch before it, which that thread has processed meanwhile or is finishing: reading,
    /// copying and writing run beside the scans' processing. The outputs of a batch follow
    /// the input records of the next one, so the file's layout depends on the input alone.
    fn hand_over(&mut self) -> anyhow::Result<()> {
        let batch = std::mem::take(&mut self.batch);
        if !batch.is_empty() {
            (self.to_process.as_ref())
                .and_then(|to| to.send(batch).ok())
                .ok_or_else(|| anyhow::anyhow!("scan processing stopped"))?;
            self.in_flight += 1;
        }
        while self.in_flight > 1 {
            self.write_processed()?;
        }
        Ok(())
    }

    /// Hands over the last batch and writes every batch's outputs.
    fn flush(&mut self) -> anyhow::Result<()> {
        self.hand_over()?;
        while self.in_flight > 0 {
            self.write_processed()?;
        }
        Ok(())
    }

    /// Writes the outputs of the oldest batch handed over, once it is processed.
    fn write_processed(&mut self) -> anyhow::Result<()> {
        let (batch, results) =
            (self.processed.recv()).map_err(|_| anyhow::anyhow!("scan processing stopped"))?;
        self.in_flight -= 1;
        for (p, result) in batch.iter().zip(results) {
            let topic_report = self.report.topics.entry(p.topic.clone()).or_default();
            match result {
                Ok((outputs, kept, (profile, strategy), failed, notes)) => {
                    for note in notes {
                        let loc = Location::message(&self.file, &p.topic, p.log_time);
                        self.report.warnings.push(Warning {
                            topic: p.topic.clone(),
                            log_time_nanos: p.log_time,
                            message: format!("{loc}: {note}"),
                        });
                    }
                    for message in failed {
                        topic_report.stage_failures += 1;
                        let loc = Location::message(&self.file, &p.topic, p.log_time);
                        self.report.warnings.push(Warning {
                            topic: p.topic.clone(),
                            log_time_nanos: p.log_time,
                            message: format!(
                                "{loc}: {message}; the scan's other channels were written"
                            ),
                        });
                    }
                    self.scans_done += 1;
                    topic_report.kept_fraction += kept;
                    topic_report.scans += 1;
                    topic_report.sensor = Some(profile.name.clone());
                    topic_report.strategy = Some(strategy.name().into());
                    topic_report.rows = profile.beams();
                    topic_report.columns = profile.columns;
                    let family = p.format.family();
                    for o in outputs {
                        let topic = format!("{}/rangegan/{}", p.topic, o.suffix);
                        let id = self.out.own_channel(&topic, family, o.kind)?;
                        self.out
                            .write_own(id, p.log_time, p.publish_time, &o.data)?;
                        self.report.outputs_written += 1;
                    }
                }
                Err(message) => {
                    topic_report.malformed += 1;
                    let loc = Location::message(&self.file, &p.topic, p.log_time);
                    self.report.warnings.push(Warning {
                        topic: p.topic.clone(),
                        log_time_nanos: p.log_time,
                        message: format!("{loc}: {message}; message copied unchanged"),
                    });
                }
            }
        }
        Ok(())
    }
}

/// Processes the batches that arrive on `batches`, one after the other (a chain's scans in
/// the next batch continue from this one's), and sends each back with its results.
fn process_batches(
    processor: &ScanProcessor<'_, '_>,
    batches: mpsc::Receiver<Vec<Pending>>,
    processed: mpsc::Sender<BatchResults>,
) {
    let mut chains = HashMap::new();
    for batch in batches {
        processor.fix_profiles(&batch);
        let results = process_batch(processor, &mut chains, &batch);
        if processed.send((batch, results)).is_err() {
            return; // the reading side stopped (an error it reports)
        }
    }
}

/// Every scan of `batch` processed, in its order: chains in parallel, each in input order;
/// unchained scans each on their own.
fn process_batch(
    processor: &ScanProcessor<'_, '_>,
    chains: &mut HashMap<ChainKey, ChainState>,
    batch: &[Pending],
) -> Vec<Result<Processed, String>> {
    let mut groups: Vec<(Option<ChainKey>, Vec<usize>)> = Vec::new();
    for (i, p) in batch.iter().enumerate() {
        let key = p.chain.map(|c| (p.topic.clone(), c));
        match groups.iter_mut().find(|(k, _)| key.is_some() && *k == key) {
            Some((_, members)) => members.push(i),
            None => groups.push((key, vec![i])),
        }
    }
    for key in groups.iter().filter_map(|(k, _)| k.clone()) {
        chains.entry(key).or_default();
    }
    let chains = &*chains;
    let done = Mutex::new(Vec::with_capacity(batch.len()));
    let finish = |i: usize, begun: Result<Begun<'_>, String>| {
        let processed = begun.map(Begun::complete);
        done.lock()
            .unwrap_or_else(|e| e.into_inner())
            .push((i, processed));
    };
    // A chain's scans start one after the other on a thread of the chain's own; each one's
    // rest goes to the rayon pool, beside the starts that follow. The decoder runs a scan
    // on a pool of its own and a rayon worker waiting for it takes up other queued work, so
    // a chain queued there would be taken up inside another chain's start, and run to its
    // end before that chain went on: both chains on one core.
    rayon::in_place_scope(|rests| {
        std::thread::scope(|chain_threads| {
            for (key, members) in &groups {
                let finish = &finish;
                match key.as_ref().and_then(|k| chains.get(k)) {
                    Some(chain) => {
                        chain_threads.spawn(move || {
                            for &i in members {
                                let begun = processor.begin(&batch[i], Some(chain));
                                rests.spawn(move |_| finish(i, begun));
                            }
                        });
                    }
                    None => {
                        for &i in members {
                            rests.spawn(move |_| finish(i, processor.begin(&batch[i], None)));
                        }
                    }
                }
            }
        });
    });
    let mut results: Vec<Option<Result<Processed, String>>> = batch.iter().map(|_| None).collect();
    for (i, r) in done.into_inner().unwrap_or_else(|e| e.into_inner()) {
        results[i] = Some(r);
    }
    results
        .into_iter()
        .map(|r| r.expect("every scan of the batch was processed"))
        .collect()
}

/// How far a conversion has come, for progress bars.
#[derive(Debug, Clone, Copy, Default)]
pub struct Progress {
    pub bytes_read: u64,
    pub scans: u64,
}

/// Converts `input` (read as a stream from `src`) into `out`: copies every record
/// and adds the channels of `stages` for every point-cloud topic. With
/// `opts.strict`, an input with anything skipped leaves no output (the temporary
/// file is discarded).
pub fn convert(
    input: &std::path::Path,
    mut src: impl Read + Seek,
    file_len: Option<u64>,
    mut out: McapOutput,
    opts: &ConvertOptions,
    stages: &[&Stage<'_>],
    mut progress: impl FnMut(Progress),
) -> anyhow::Result<ConvertReport> {
    out.write_metadata("rangegan", opts.metadata.clone())?;
    if let Some(summary) =
        file_len.and_then(|len| crate::io::reader::Summary::read(&mut src, len).ok())
    {
        out.reserve_input_topics(summary.channels.values().map(|c| c.topic.as_str()));
    }
    let mut processor = ScanProcessor {
        opts,
        stages,
        profiles: Mutex::new(HashMap::new()),
        file: input.to_path_buf(),
        fit_warnings: Mutex::new(Vec::new()),
        coverage: Mutex::new(HashMap::new()),
        census: HashMap::new(),
        fill_checks: HashMap::new(),
    };
    survey::survey(&mut processor, &mut src, file_len);
    let processor = &processor;
    let (to_process, batches) = mpsc::channel();
    let (results, processed) = mpsc::channel();
    let mut conv = Converter {
        out,
        opts,
        file: input.to_path_buf(),
        table: ChannelTable::default(),
        batch: Vec::new(),
        topic_scans: HashMap::new(),
        to_process: Some(to_process),
        processed,
        in_flight: 0,
        scans_done: 0,
        report: ConvertReport::default(),
    };
    let read = std::thread::scope(|scope| {
        scope.spawn(move || process_batches(processor, batches, results));
        let scans = std::cell::Cell::new(0u64);
        let read = read_records(
            src,
            file_len,
            opts.on_error,
            |rec| {
                conv.visit(rec)?;
                scans.set(conv.scans_done);
                Ok(())
            },
            |bytes_read| {
                progress(Progress {
                    bytes_read,
                    scans: scans.get(),
                })
            },
        )
        .map_err(|e| match e {
            // Write errors already name the output.
            crate::io::reader::ReadError::Visitor(e) => e,
            e => anyhow::anyhow!("{}: {e}", input.display()),
        });
        let read = read.and_then(|read| conv.flush().map(|()| read));
        conv.to_process = None;
        read
    })?;
    let mut report = conv.report;
    report.read = read;
    report.copied = conv.out.copied;
    report
        .warnings
        .extend(conv.out.notes.drain(..).map(|message| Warning {
            topic: String::new(),
            log_time_nanos: 0,
            message: format!("{}: {message}", input.display()),
        }));
    report.model_fit = std::mem::take(
        &mut processor
            .fit_warnings
            .lock()
            .unwrap_or_else(|e| e.into_inner()),
    );
    for t in report.topics.values_mut() {
        if t.scans > 0 {
            t.kept_fraction /= t.scans as f64;
        }
    }
    if opts.strict && report.skipped_anything() {
        conv.out.discard_and_clear_target()?;
    } else {
        conv.out.finish()?;
    }
    Ok(report)
}

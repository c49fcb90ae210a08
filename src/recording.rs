//! One point-cloud topic of a recording as range images, for commands that need
//! whole recordings in memory (`diagnose`, `render`): reads the MCAP stream,
//! decodes every cloud of the topic, projects it onto one sensor profile, and
//! keeps the recording's `rangegan.simulate` metadata (sensor, physics, speed).

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use anyhow::Context;
use mcap::records::Record;

use crate::error::Location;
use crate::io::{ChannelTable, CloudFormat, DecodedCloud, OnError, decode_cloud, read_records};
use crate::lidar::projection::choose_strategy;
use crate::lidar::sweep::Seam;
use crate::lidar::{RangeImage, SensorProfile, Strategy, estimate_profile, project};

/// How to pick the projection grid.
#[derive(Debug, Clone, PartialEq)]
pub enum Grid {
    /// This profile.
    Fixed(SensorProfile),
    /// The recording's `rangegan.simulate` sensor if it has one, else estimated
    /// from its first scan; `columns` (if given) replaces the profile's.
    FromRecording { columns: Option<usize> },
}

/// A topic's scans.
#[derive(Debug, Clone)]
pub struct Recording {
    pub topic: String,
    pub format: CloudFormat,
    pub profile: SensorProfile,
    pub images: Vec<RangeImage>,
    /// Log time of each scan, nanoseconds.
    pub log_times: Vec<u64>,
    /// Where each scan's sweep starts, where its cloud's firing order says.
    pub seams: Vec<Option<Seam>>,
    /// Whether the clouds were organized (beams x columns).
    pub organized: bool,
    /// Metadata records by name.
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// Messages of the topic that could not be decoded or projected.
    pub skipped: Vec<String>,
    /// The sensor that made the recording, where known: its `simulate` profile, or the
    /// profile estimated from its first scan (whatever grid the scans were projected on).
    pub own_sensor: Option<SensorProfile>,
}

impl Recording {
    /// The `rangegan.simulate` physics entries, if the recording has them.
    pub fn physics(&self) -> serde_json::Map<String, serde_json::Value> {
        self.metadata
            .get("rangegan.simulate")
            .and_then(|m| m.get("physics"))
            .and_then(|p| serde_json::from_str::<serde_json::Value>(p).ok())
            .and_then(|v| v.as_object().cloned())
            .map(|mut m| {
                m.remove("description");
                m
            })
            .unwrap_or_default()
    }

    /// The ego speed written by `simulate`, m/s.
    pub fn speed_mps(&self) -> Option<f64> {
        self.metadata
            .get("rangegan.simulate")
            .and_then(|m| m.get("speed_mps"))
            .and_then(|s| s.parse().ok())
    }

    /// The sensor profile written by `simulate`.
    pub fn simulated_profile(
        metadata: &BTreeMap<String, BTreeMap<String, String>>,
    ) -> Option<SensorProfile> {
        metadata
            .get("rangegan.simulate")
            .and_then(|m| m.get("sensor"))
            .and_then(|s| serde_json::from_str(s).ok())
    }
}

/// Whether two sensor profiles are different sensors by their beam counts: projected on one
/// grid, the smaller one's scans would leave rows empty that read as dead beams. Estimated
/// counts can be off by the beams that saw nothing in one scan (a real beam dropout among
/// them), so only counts half again apart tell two sensors apart.
pub fn other_sensors(a: &SensorProfile, b: &SensorProfile) -> bool {
    let (na, nb) = (a.beams().max(1), b.beams().max(1));
    2 * na.max(nb) >= 3 * na.min(nb)
}

/// A message of the topic, kept until the grid is known.
struct Raw {
    log_time: u64,
    cloud: DecodedCloud,
}

/// Reads `topic` (or the only / first point-cloud topic) of `path`, each point's
/// row found by the strategy chosen from the first scan.
pub fn read(path: &Path, topic: Option<&str>, grid: &Grid) -> anyhow::Result<Recording> {
    read_with(path, topic, grid, Strategy::Auto)
}

/// As [`read`] with a given projection strategy (`Auto`: chosen from the first scan).
pub fn read_with(
    path: &Path,
    topic: Option<&str>,
    grid: &Grid,
    strategy: Strategy,
) -> anyhow::Result<Recording> {
    let file =
        std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let len = file.metadata().ok().map(|m| m.len());
    let mut table = ChannelTable::default();
    let mut clouds: HashMap<u16, (String, CloudFormat)> = HashMap::new();
    let mut chosen: Option<(String, CloudFormat)> = None;
    let mut metadata = BTreeMap::new();
    let mut raws: Vec<Raw> = Vec::new();
    let mut skipped = Vec::new();
    let mut cloud_topics: Vec<String> = Vec::new();
    read_records(
        std::io::BufReader::new(file),
        len,
        OnError::Fail,
        |record| {
            if let Some((id, entry)) = table.observe(record)
                && let Some(format) = entry.cloud
            {
                if !cloud_topics.contains(&entry.topic) {
                    cloud_topics.push(entry.topic.clone());
                }
                let wanted = topic.is_none_or(|t| t == entry.topic);
                if wanted && chosen.as_ref().is_none_or(|(t, _)| *t == entry.topic) {
                    chosen = Some((entry.topic.clone(), format));
                    clouds.insert(id, (entry.topic.clone(), format));
                }
            }
            match record {
                Record::Metadata(m) => {
                    metadata.insert(m.name.clone(), m.metadata.clone());
                }
                Record::Message { header, data } => {
                    if let Some((t, format)) = clouds.get(&header.channel_id) {
                        match decode_cloud(*format, data) {
                            Ok(cloud) => raws.push(Raw {
                                log_time: header.log_time,
                                cloud,
                            }),
                            Err(e) => skipped.push(format!(
                                "{}: {e}",
                                Location::message(path, t, header.log_time)
                            )),
                        }
                    }
                }
                _ => {}
            }
            Ok(())
        },
        |_| {},
    )
    .map_err(|e| e.for_strict_reader(path))?;
    let Some((topic_name, format)) = chosen else {
        anyhow::bail!(
            "{}: {}",
            path.display(),
            match topic {
                Some(t) => format!(
                    "no point-cloud topic {t} (point-cloud topics: {})",
                    if cloud_topics.is_empty() {
                        "none".to_string()
                    } else {
                        cloud_topics.join(", ")
                    }
                ),
                None => "no point-cloud topic (PointCloud2 or foxglove.PointCloud)".into(),
            }
        );
    };
    anyhow::ensure!(
        !raws.is_empty(),
        "{}: topic {topic_name} has no readable scans ({} skipped{})",
        path.display(),
        skipped.len(),
        skipped
            .first()
            .map(|s| format!(": {s}"))
            .unwrap_or_default()
    );
    let own_sensor = || -> anyhow::Result<SensorProfile> {
        match Recording::simulated_profile(&metadata) {
            Some(p) => Ok(p),
            None => Ok(estimate_profile(std::slice::from_ref(&raws[0].cloud.scan))
                .map_err(|e| {
                    anyhow::anyhow!(
                        "{}: cannot estimate the sensor from the first scan: {e}; give --sensor",
                        Location::message(path, &topic_name, raws[0].log_time)
                    )
                })?
                .profile),
        }
    };
    let own = own_sensor();
    let profile = match grid {
        Grid::Fixed(p) => p.clone(),
        Grid::FromRecording { columns } => {
            let p = match &own {
                Ok(p) => p.clone(),
                Err(e) => anyhow::bail!("{e}"),
            };
            match columns {
                Some(c) => p.with_columns(*c),
                None => p,
            }
        }
    };
    let strategy = match strategy {
        Strategy::Auto => choose_strategy(&raws[0].cloud.scan, &profile),
        given => given,
    };
    let organized = raws[0].cloud.scan.is_organized();
    let mut images = Vec::new();
    let mut log_times = Vec::new();
    let mut seams = Vec::new();
    for raw in &raws {
        match project(&raw.cloud.scan, &profile, strategy) {
            Ok(img) => {
                seams.push(Seam::find(&raw.cloud.scan, &img));
                images.push(img);
                log_times.push(raw.log_time);
            }
            Err(e) => skipped.push(format!(
                "{}: {e}",
                Location::message(path, &topic_name, raw.log_time)
            )),
        }
    }
    anyhow::ensure!(
        !images.is_empty(),
        "{}: no scan of {topic_name} could be projected onto {}: {}",
        path.display(),
        profile.name,
        skipped.first().cloned().unwrap_or_default()
    );
    Ok(Recording {
        topic: topic_name,
        format,
        profile,
        images,
        log_times,
        seams,
        organized,
        metadata,
        skipped,
        own_sensor: own.ok(),
    })
}

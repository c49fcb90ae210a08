//! `rangegan-mcap info IN`: what a recording holds and how its clouds project.

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::Context;
use mcap::records::Record;

use super::{GlobalArgs, Outcome};
use crate::io::{ChannelTable, CloudFormat, OnError, decode_cloud, read_records};
use crate::lidar::estimate_profile;
use crate::lidar::{Strategy, project};
use crate::pipeline::SensorChoice;

#[derive(Debug, clap::Args)]
pub struct InfoArgs {
    /// MCAP recording.
    pub input: PathBuf,
    /// Sensor profile for the projection report (`auto`, a built-in name or a JSON file).
    #[arg(long, default_value = "auto")]
    pub sensor: String,
}

#[derive(Debug, Default, serde::Serialize)]
struct ChannelInfo {
    id: u16,
    topic: String,
    schema: String,
    schema_encoding: String,
    message_encoding: String,
    messages: u64,
    first_log_time: Option<u64>,
    last_log_time: Option<u64>,
    point_cloud: Option<CloudFormat>,
    layout: Option<CloudLayoutInfo>,
}

#[derive(Debug, serde::Serialize)]
struct CloudLayoutInfo {
    height: usize,
    width: usize,
    returns: usize,
    fields: Vec<String>,
    sensor: String,
    beams: usize,
    columns: usize,
    strategy: String,
    kept_fraction: f64,
    estimate: Option<String>,
    error: Option<String>,
}

fn median_spread(est: &crate::lidar::SensorEstimate) -> f32 {
    let mut s: Vec<f32> = est.beams.iter().map(|b| b.spread_deg).collect();
    s.sort_by(f32::total_cmp);
    s.get(s.len() / 2).copied().unwrap_or(0.0)
}

pub fn run(global: &GlobalArgs, args: InfoArgs) -> anyhow::Result<Outcome> {
    let file = std::fs::File::open(&args.input)
        .with_context(|| format!("cannot open {}", args.input.display()))?;
    let len = file.metadata().ok().map(|m| m.len());
    let sensor = super::convert::sensor_choice(&args.sensor)?;
    let mut table = ChannelTable::default();
    let mut channels: BTreeMap<u16, ChannelInfo> = BTreeMap::new();
    let (mut attachments, mut metadata) = (Vec::new(), Vec::new());
    let reader = std::io::BufReader::with_capacity(1 << 20, file);
    let report = read_records(
        reader,
        len,
        OnError::Skip,
        |rec| {
            if let Some((id, c)) = table.observe(rec) {
                channels.entry(id).or_insert_with(|| ChannelInfo {
                    id,
                    topic: c.topic.clone(),
                    schema: c.schema.clone(),
                    schema_encoding: c.schema_encoding.clone(),
                    message_encoding: c.message_encoding.clone(),
                    point_cloud: c.cloud,
                    ..Default::default()
                });
            }
            match rec {
                Record::Message { header, data } => {
                    if let Some(ch) = channels.get_mut(&header.channel_id) {
                        ch.messages += 1;
                        ch.first_log_time = Some(
                            ch.first_log_time
                                .map_or(header.log_time, |t| t.min(header.log_time)),
                        );
                        ch.last_log_time = Some(
                            ch.last_log_time
                                .map_or(header.log_time, |t| t.max(header.log_time)),
                        );
                        if let (Some(format), None) = (ch.point_cloud, &ch.layout) {
                            ch.layout = Some(describe(format, data, &sensor));
                        }
                    }
                }
                Record::Attachment { header, data, .. } => {
                    attachments.push((header.name.clone(), data.len()))
                }
                Record::Metadata(m) => metadata.push(m.name.clone()),
                _ => {}
            }
            Ok(())
        },
        |_| {},
    )
    .map_err(|e| anyhow::anyhow!("{}: {e}", args.input.display()))?;

    if global.json {
        let out = serde_json::json!({
            // Displayed, not serialised: a path that is not UTF-8 has no JSON string.
            "file": args.input.display().to_string(),
            "bytes": len,
            "complete": report.complete,
            "read": report,
            "channels": channels.values().collect::<Vec<_>>(),
            "attachments": attachments,
            "metadata": metadata,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(Outcome::Success);
    }
    println!(
        "{}: {} bytes{}",
        args.input.display(),
        len.unwrap_or(0),
        if report.complete { "" } else { " (incomplete)" }
    );
    if let Some(why) = &report.stopped {
        println!("  warning: {why}; {} bytes unread", report.unread_bytes);
    }
    for c in &report.bad_chunks {
        println!("  warning: {c}");
    }
    for r in &report.bad_records {
        println!("  warning: skipped {r}");
    }
    println!("channels:");
    for ch in channels.values() {
        println!(
            "  {:>4} {} [{} / {}] {} messages",
            ch.id, ch.topic, ch.schema, ch.message_encoding, ch.messages
        );
        if let (Some(first), Some(last)) = (ch.first_log_time, ch.last_log_time) {
            println!("       {}", time_span(first, last, ch.messages));
        }
        if let Some(l) = &ch.layout {
            println!(
                "       point cloud {}x{} ({} returns), fields {}",
                l.height,
                l.width,
                l.returns,
                l.fields.join(",")
            );
            if let Some(e) = &l.estimate {
                println!("       estimated sensor: {e}");
            }
            match &l.error {
                Some(e) => println!("       cannot project: {e}"),
                None => println!(
                    "       sensor {} ({} beams x {} columns), projection {}, {:.1} % of returns keep a pixel",
                    l.sensor,
                    l.beams,
                    l.columns,
                    l.strategy,
                    100.0 * l.kept_fraction
                ),
            }
        }
    }
    if !attachments.is_empty() {
        println!(
            "attachments: {}",
            attachments
                .iter()
                .map(|a| a.0.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    if !metadata.is_empty() {
        println!("metadata: {}", metadata.join(", "));
    }
    Ok(Outcome::Success)
}

/// `2024-01-01 00:00:00.000 UTC, 12.300 s, 10.0 Hz`: when a topic starts, how long it lasts
/// and its mean rate (log times).
fn time_span(first: u64, last: u64, messages: u64) -> String {
    let secs = last.saturating_sub(first) as f64 / 1e9;
    let rate = if messages > 1 && secs > 0.0 {
        format!(", {:.1} Hz", (messages - 1) as f64 / secs)
    } else {
        String::new()
    };
    format!("from {}, {secs:.3} s{rate}", utc(first))
}

/// A log time as a UTC date (days-from-civil inverse, proleptic Gregorian).
fn utc(nanos: u64) -> String {
    let secs = nanos / 1_000_000_000;
    let (days, rest) = ((secs / 86_400) as i64, secs % 86_400);
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1_460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02} {:02}:{:02}:{:02}.{:03} UTC",
        rest / 3600,
        rest / 60 % 60,
        rest % 60,
        nanos % 1_000_000_000 / 1_000_000
    )
}

fn describe(format: CloudFormat, data: &[u8], sensor: &SensorChoice) -> CloudLayoutInfo {
    let mut info = CloudLayoutInfo {
        height: 0,
        width: 0,
        returns: 0,
        fields: Vec::new(),
        sensor: String::new(),
        beams: 0,
        columns: 0,
        strategy: String::new(),
        kept_fraction: 0.0,
        estimate: None,
        error: None,
    };
    let cloud = match decode_cloud(format, data) {
        Ok(c) => c,
        Err(e) => {
            info.error = Some(e.to_string());
            return info;
        }
    };
    let scan = &cloud.scan;
    info.height = scan.height;
    info.width = scan.width;
    info.returns = scan.returns();
    info.fields = ["intensity", "ring", "time", "label"]
        .into_iter()
        .zip([
            scan.intensity.is_some(),
            scan.ring.is_some(),
            scan.time_s.is_some(),
            scan.label.is_some(),
        ])
        .filter(|(_, has)| *has)
        .map(|(n, _)| n.to_string())
        .collect();
    info.fields.insert(0, "xyz".into());
    let profile = match sensor {
        SensorChoice::Fixed(p) => p.clone(),
        SensorChoice::Auto => match estimate_profile(std::slice::from_ref(scan)) {
            Ok(est) => {
                info.estimate = Some(format!(
                    "{} beams by {}, elevations {:+.2} to {:+.2} deg (median spread {:.2} deg), {} columns, {:.1}-{:.1} m",
                    est.beams.len(),
                    est.method.name(),
                    est.beams.first().map_or(0.0, |b| b.elevation_deg),
                    est.beams.last().map_or(0.0, |b| b.elevation_deg),
                    median_spread(&est),
                    est.columns,
                    est.min_range_m,
                    est.max_range_m
                ));
                est.profile
            }
            Err(e) => {
                info.error = Some(e.to_string());
                return info;
            }
        },
    };
    let strategy = crate::lidar::projection::choose_strategy(scan, &profile);
    info.sensor = profile.name.clone();
    info.beams = profile.beams();
    info.columns = profile.columns;
    info.strategy = strategy.name().into();
    match project(scan, &profile, Strategy::Auto) {
        Ok(img) => info.kept_fraction = img.valid_count() as f64 / info.returns.max(1) as f64,
        Err(e) => info.error = Some(e.to_string()),
    }
    info
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_times_read_as_utc_dates_with_rates() {
        assert_eq!(utc(0), "1970-01-01 00:00:00.000 UTC");
        assert_eq!(
            utc(1_704_067_200_250_000_000),
            "2024-01-01 00:00:00.250 UTC"
        );
        assert_eq!(utc(951_825_600_000_000_000), "2000-02-29 12:00:00.000 UTC");
        assert_eq!(
            time_span(1_000_000_000, 2_000_000_000, 11),
            "from 1970-01-01 00:00:01.000 UTC, 1.000 s, 10.0 Hz"
        );
        assert_eq!(
            time_span(5, 5, 1),
            "from 1970-01-01 00:00:00.000 UTC, 0.000 s"
        );
    }
}

//! `rangegan-mcap layout OUT.mcap`: a Foxglove layout for a converted recording's own topics.
//!
//! For every point-cloud topic `T` that `convert` added channels to, the layout shows the
//! input cloud and the completed cloud in 3D, and every `T/rangegan/*` image (range, depth,
//! x_d, x_n, masks, other grids) as an image panel, each scaled to what it holds (metres,
//! probabilities, masks). Only topics with messages in the recording are named, so every
//! panel opens filled.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;

use anyhow::Context;
use mcap::records::Record;
use serde_json::{Value, json};

use super::{GlobalArgs, Outcome};
use crate::io::{ChannelTable, OnError, read_records};

#[derive(Debug, clap::Args)]
pub struct LayoutArgs {
    /// A recording written by `convert`.
    pub input: PathBuf,
    /// Where to write the layout (default: beside the input, `NAME.foxglove-layout.json`).
    #[arg(long, short)]
    pub output: Option<PathBuf>,
}

/// The infix `convert` puts between a cloud topic and its channels.
const INFIX: &str = "/rangegan/";

pub fn run(global: &GlobalArgs, args: LayoutArgs) -> anyhow::Result<Outcome> {
    let file = std::fs::File::open(&args.input)
        .with_context(|| format!("cannot open {}", args.input.display()))?;
    let len = file.metadata().ok().map(|m| m.len());
    let mut table = ChannelTable::default();
    let mut topics: BTreeMap<u16, String> = BTreeMap::new();
    let mut with_messages: BTreeSet<String> = BTreeSet::new();
    read_records(
        std::io::BufReader::with_capacity(1 << 20, file),
        len,
        OnError::Skip,
        |rec| {
            if let Some((id, c)) = table.observe(rec) {
                topics.insert(id, c.topic.clone());
            }
            if let Record::Message { header, .. } = rec
                && let Some(t) = topics.get(&header.channel_id)
            {
                with_messages.insert(t.clone());
            }
            Ok(())
        },
        |_| {},
    )
    .with_context(|| format!("failed to read {}", args.input.display()))?;
    let layout = layout_for(&with_messages);
    anyhow::ensure!(
        layout["configById"]
            .as_object()
            .is_some_and(|p| !p.is_empty()),
        "{}: no channels written by `rangegan-mcap convert` (topics named .../rangegan/...)",
        args.input.display()
    );
    let output = args.output.unwrap_or_else(|| {
        let stem = args.input.file_stem().unwrap_or_default().to_string_lossy();
        args.input
            .with_file_name(format!("{stem}.foxglove-layout.json"))
    });
    crate::util::fs::write_atomic(&output, serde_json::to_string_pretty(&layout)?.as_bytes())
        .with_context(|| format!("failed to write {}", output.display()))?;
    if !global.quiet {
        eprintln!(
            "{}: layout of {} panels",
            output.display(),
            panel_count(&layout)
        );
    }
    Ok(Outcome::Success)
}

fn panel_count(layout: &Value) -> usize {
    layout["configById"].as_object().map_or(0, |p| p.len())
}

/// The layout of the converted topics among `topics` (those with messages).
pub fn layout_for(topics: &BTreeSet<String>) -> Value {
    let mut panels = serde_json::Map::new();
    let mut ids = Vec::new();
    let clouds: BTreeSet<&str> = topics
        .iter()
        .filter_map(|t| t.split_once(INFIX).map(|(cloud, _)| cloud))
        .collect();
    for (n, cloud) in clouds.iter().enumerate() {
        let mut add = |id: String, panel: Value| {
            ids.push(id.clone());
            panels.insert(id, panel);
        };
        if topics.contains(*cloud) {
            add(
                format!("3D!input{n}"),
                cloud_panel(&format!("{cloud} (input)"), cloud, None),
            );
        }
        let prefix = format!("{cloud}{INFIX}");
        for topic in topics.iter().filter(|t| t.starts_with(&prefix)) {
            let channel = &topic[prefix.len()..];
            let id = format!("{n}{}", channel.replace(['/', ' '], "_"));
            if channel == "points" || channel.starts_with("points_") {
                let title = format!("{cloud}: completed cloud {channel} (colour = x_n)");
                add(
                    format!("3D!{id}"),
                    cloud_panel(&title, topic, Some("raydrop_prob")),
                );
            } else {
                add(format!("Image!{id}"), image_panel(cloud, channel, topic));
            }
        }
    }
    json!({
        "configById": panels,
        "globalVariables": {},
        "userNodes": {},
        "linkedGlobalVariables": [],
        "playbackConfig": { "speed": 1 },
        "layout": split(&ids, "row"),
    })
}

/// A balanced tree of splits over the panels, alternating rows and columns.
fn split(ids: &[String], direction: &str) -> Value {
    match ids.len() {
        0 => Value::Null,
        1 => Value::String(ids[0].clone()),
        n => {
            let other = if direction == "row" { "column" } else { "row" };
            let half = n.div_ceil(2);
            json!({
                "first": split(&ids[..half], other),
                "second": split(&ids[half..], other),
                "direction": direction,
                "splitPercentage": 100.0 * half as f64 / n as f64,
            })
        }
    }
}

fn cloud_panel(title: &str, topic: &str, colour_field: Option<&str>) -> Value {
    let mut settings =
        json!({ "visible": true, "pointSize": 2, "colorMode": "colormap", "colorMap": "turbo" });
    if let Some(f) = colour_field {
        settings["colorField"] = json!(f);
    }
    json!({
        "title": title,
        "cameraState": {
            "distance": 60, "perspective": true, "phi": 50, "thetaOffset": 180,
            "target": [0, 0, 0], "targetOffset": [0, 0, 0], "targetOrientation": [0, 0, 0, 1],
            "fovy": 45, "near": 0.5, "far": 5000
        },
        "scene": {},
        "transforms": {},
        "layers": {},
        "topics": { topic: settings },
    })
}

/// An image panel scaled to what the channel holds.
fn image_panel(cloud: &str, channel: &str, topic: &str) -> Value {
    let (what, min, max, map) = match channel {
        "raydrop_prob" => ("x_n = P(ray dropped)", 0.0, 1.0, "rainbow"),
        c if c.starts_with("raydrop_mask") => {
            ("sampled ray-drop mask (255 = kept)", 0.0, 255.0, "rainbow")
        }
        "range" => ("measured range (m)", 0.0, 80.0, "turbo"),
        "depth" => ("depth: returns, x_d where none (m)", 0.0, 80.0, "turbo"),
        "x_d" => ("x_d, the decoded depth (m)", 0.0, 80.0, "turbo"),
        _ => ("depth on another grid (m)", 0.0, 80.0, "turbo"),
    };
    json!({
        "title": format!("{cloud}: {channel}: {what}"),
        "imageMode": {
            "imageTopic": topic,
            "colorMode": "colormap",
            "colorMap": map,
            "minValue": min,
            "maxValue": max
        },
        "topics": {}
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_converted_channel_gets_one_panel_and_the_tree_holds_them_all() {
        let topics: BTreeSet<String> = [
            "/ouster/points",
            "/ouster/points/rangegan/range",
            "/ouster/points/rangegan/depth",
            "/ouster/points/rangegan/x_d",
            "/ouster/points/rangegan/raydrop_prob",
            "/ouster/points/rangegan/raydrop_mask",
            "/ouster/points/rangegan/points",
            "/ouster/points/rangegan/depth_vlp16",
            "/ouster/points/rangegan/points_vlp16",
            "/imu",
        ]
        .map(String::from)
        .into();
        let layout = layout_for(&topics);
        assert_eq!(panel_count(&layout), 9);
        fn leaves(v: &Value, out: &mut Vec<String>) {
            match v {
                Value::String(s) => out.push(s.clone()),
                Value::Object(o) => {
                    leaves(&o["first"], out);
                    leaves(&o["second"], out);
                }
                _ => {}
            }
        }
        let mut ids = Vec::new();
        leaves(&layout["layout"], &mut ids);
        ids.sort();
        let mut panels: Vec<String> = layout["configById"]
            .as_object()
            .unwrap()
            .keys()
            .cloned()
            .collect();
        panels.sort();
        assert_eq!(ids, panels);
        assert!(!layout.to_string().contains("/imu"));
    }
}

//! Where a problem happened: the file, topic and log time shared by every error and warning.

use std::fmt;
use std::path::PathBuf;

/// The place in a recording that an error or warning talks about.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Location {
    pub file: PathBuf,
    pub topic: Option<String>,
    pub log_time_nanos: Option<u64>,
}

impl Location {
    pub fn file(file: impl Into<PathBuf>) -> Self {
        Location {
            file: file.into(),
            ..Default::default()
        }
    }

    pub fn message(file: impl Into<PathBuf>, topic: &str, log_time_nanos: u64) -> Self {
        Location {
            file: file.into(),
            topic: Some(topic.to_string()),
            log_time_nanos: Some(log_time_nanos),
        }
    }
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        if let Some(topic) = &self.topic {
            write!(f, ": {topic}")?;
        }
        if let Some(t) = self.log_time_nanos {
            write!(f, " @ {}.{:09} s", t / 1_000_000_000, t % 1_000_000_000)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn location_names_file_topic_and_time() {
        let loc = Location::message("in.mcap", "/velodyne_points", 1_317_022_740_129_000_001);
        assert_eq!(
            loc.to_string(),
            "in.mcap: /velodyne_points @ 1317022740.129000001 s"
        );
        assert_eq!(Location::file("a.mcap").to_string(), "a.mcap");
    }
}

//! Calendar dates as seconds since the Unix epoch (UTC, proleptic Gregorian), without a
//! time-zone database: what stamping recordings from files' own dates needs.

/// Days since 1970-01-01 of the civil date `y-m-d` (Howard Hinnant's algorithm).
pub fn days_from_civil(y: i64, m: u32, d: u32) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (i64::from(m) + 9) % 12;
    let doy = (153 * mp + 2) / 5 + i64::from(d) - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

/// Seconds since the epoch of `YYYY-MM-DD HH:MM:SS[.fraction]` (UTC), or `None` when the text
/// is not such a date.
pub fn parse_utc(text: &str) -> Option<f64> {
    let (date, time) = text.trim().split_once([' ', 'T'])?;
    let mut d = date.split('-').map(|p| p.parse::<i64>().ok());
    let (y, m, day) = (d.next()??, d.next()??, d.next()??);
    let mut t = time.split(':');
    let (h, mi) = (
        t.next()?.parse::<i64>().ok()?,
        t.next()?.parse::<i64>().ok()?,
    );
    let s = t.next()?.parse::<f64>().ok()?;
    let valid = (1..=12).contains(&m)
        && (1..=31).contains(&day)
        && (0..24).contains(&h)
        && (0..60).contains(&mi)
        && (0.0..61.0).contains(&s);
    valid.then(|| {
        (days_from_civil(y, m as u32, day as u32) * 86_400 + h * 3600 + mi * 60) as f64 + s
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_dates_and_refusals() {
        assert_eq!(days_from_civil(1970, 1, 1), 0);
        assert_eq!(days_from_civil(2000, 3, 1), 11_017);
        let t = parse_utc("2011-09-26 13:10:51.158069617").expect("date");
        assert!((t - 1_317_042_651.158_069_6).abs() < 1e-3, "{t}");
        assert_eq!(parse_utc("2020-01-01 00:00:00"), Some(1_577_836_800.0));
        assert_eq!(parse_utc("2020-13-01 00:00:00"), None);
        assert_eq!(parse_utc("yesterday"), None);
    }
}

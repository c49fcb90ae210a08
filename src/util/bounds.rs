//! Bounds on sizes that come from outside (a model folder's config, a count flag): a size is
//! checked before anything is allocated from it, so a hostile or mistyped file gets an error
//! naming the field, never a panic or a huge allocation.

use std::ops::RangeInclusive;

use anyhow::{Result, ensure};

/// `value` lies in `range`, or an error naming `what`.
pub fn size(what: &str, value: usize, range: RangeInclusive<usize>) -> Result<()> {
    ensure!(
        range.contains(&value),
        "{what} is {value}; it must be between {} and {}",
        range.start(),
        range.end()
    );
    Ok(())
}

/// A list of sizes: its length in `len`, every entry in `each`.
pub fn sizes(
    what: &str,
    values: &[usize],
    len: RangeInclusive<usize>,
    each: RangeInclusive<usize>,
) -> Result<()> {
    size(&format!("the length of {what}"), values.len(), len)?;
    for (i, v) in values.iter().enumerate() {
        size(&format!("{what}[{i}]"), *v, each.clone())?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_outside_their_range_are_named() {
        assert!(size("width", 5, 1..=8).is_ok());
        let err = size("width", 0, 1..=8).unwrap_err().to_string();
        assert!(err.contains("width is 0"), "{err}");
        assert!(sizes("widths", &[16, 32], 1..=8, 1..=1024).is_ok());
        let err = sizes("widths", &[16, 100_000], 1..=8, 1..=1024).unwrap_err();
        assert!(err.to_string().contains("widths[1] is 100000"), "{err}");
        assert!(sizes("widths", &[], 1..=8, 1..=1024).is_err());
    }
}

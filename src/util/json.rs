//! JSON helpers.

use serde_json::Value;

/// Writes `over` onto `base`: objects merge key by key (recursively), anything else replaces.
/// Reading a saved config over the current defaults this way lets files written before a
/// field existed load with that field's default.
pub fn merge(base: &mut Value, over: Value) {
    match (base, over) {
        (Value::Object(b), Value::Object(o)) => {
            for (k, v) in o {
                match b.get_mut(&k) {
                    Some(slot) => merge(slot, v),
                    None => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (slot, v) => *slot = v,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn saved_values_win_and_missing_ones_keep_their_default() {
        let mut base = serde_json::json!({"a": 1, "b": {"c": 2, "d": 3}});
        merge(&mut base, serde_json::json!({"b": {"c": 5}, "e": [1]}));
        assert_eq!(
            base,
            serde_json::json!({"a": 1, "b": {"c": 5, "d": 3}, "e": [1]})
        );
    }
}

use super::*;

#[test]
fn scan_seed_depends_on_topic_and_time() {
    assert_eq!(scan_seed("/a", 5), scan_seed("/a", 5));
    assert_ne!(scan_seed("/a", 5), scan_seed("/b", 5));
    assert_ne!(scan_seed("/a", 5), scan_seed("/a", 6));
}

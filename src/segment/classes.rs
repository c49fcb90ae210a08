//! The classes the Sim2Real segmentation benchmark scores, and how SemanticKITTI label ids
//! (what `simulate` and `import` write in a cloud's `label` field) map onto them.

/// Network outputs, in order. `other` (every other labelled surface: terrain, fence, trunk,
/// signs, ...) is trained so the named classes are not forced onto it, but it is not scored.
pub const CLASSES: [&str; 8] = [
    "car",
    "person",
    "road",
    "sidewalk",
    "building",
    "vegetation",
    "pole",
    "other",
];

use crate::lidar::kitti_boxes::IN_VIEW_NO_BOX;

/// Number of network outputs.
pub const NUM_CLASSES: usize = CLASSES.len();

/// The catch-all class.
pub const OTHER: u8 = 7;

/// The classes in the mean IoU: all but `other`.
pub const SCORED: std::ops::Range<usize> = 0..7;

/// The two classes of the paper's Table 4.
pub const CAR_PERSON: [usize; 2] = [0, 1];

/// Target of a pixel that has no class: no return, unlabelled or outlier.
pub const IGNORE: u8 = u8::MAX;

/// Target of a pixel known to be neither car nor person, and nothing more (a KITTI object
/// frame's view outside every box, see [`crate::lidar::kitti_boxes`]): a partial label.
pub const NOT_CAR_OR_PERSON: u8 = u8::MAX - 1;

/// Whether a target names one class (not [`IGNORE`], not a partial label).
pub fn is_class(target: u8) -> bool {
    (target as usize) < NUM_CLASSES
}

/// The class of a SemanticKITTI label (low 16 bits: class id; high 16: instance).
pub fn class_of(label: u32) -> u8 {
    match label & 0xffff {
        0 | 1 => IGNORE, // unlabelled, outlier
        id if id == IN_VIEW_NO_BOX => NOT_CAR_OR_PERSON,
        10 | 252 => 0, // car, moving car
        30 | 254 => 1, // person, moving person
        40 => 2,       // road
        48 => 3,       // sidewalk
        50 => 4,       // building
        70 => 5,       // vegetation
        80 => 6,       // pole
        _ => OTHER,
    }
}

/// Display colour of a class (SemanticKITTI's palette where it has one).
pub fn color(class: u8) -> [u8; 3] {
    match class {
        0 => [100, 150, 245],
        1 => [255, 30, 30],
        2 => [255, 0, 255],
        3 => [75, 0, 75],
        4 => [255, 200, 0],
        5 => [0, 175, 0],
        6 => [255, 240, 150],
        OTHER => [110, 110, 110],
        NOT_CAR_OR_PERSON => [45, 45, 45],
        _ => [0, 0, 0],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn semantickitti_ids_map_to_classes_and_instances_are_ignored() {
        assert_eq!(class_of(10), 0);
        assert_eq!(class_of((7 << 16) | 252), 0);
        assert_eq!(class_of(30), 1);
        assert_eq!(class_of(254), 1);
        assert_eq!(class_of(40), 2);
        assert_eq!(class_of(72), OTHER);
        assert_eq!(class_of(0), IGNORE);
        assert_eq!(class_of(1), IGNORE);
        assert_eq!(class_of(IN_VIEW_NO_BOX), NOT_CAR_OR_PERSON);
        assert!(!is_class(NOT_CAR_OR_PERSON) && !is_class(IGNORE) && is_class(OTHER));
        assert_eq!(
            CAR_PERSON,
            [0, 1],
            "the partial label's loss relies on this order"
        );
        assert_eq!(CLASSES[OTHER as usize], "other");
        assert!(!SCORED.contains(&(OTHER as usize)));
    }
}

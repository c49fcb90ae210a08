//! Holes in a range image (pixels without a return): how far each lies from the nearest
//! return. Images are row-major `height x width`, 0 = no return; columns wrap around (a
//! full revolution).

use std::collections::VecDeque;

/// The 4-neighbours of pixel `k` on a `height x width` image: the pixels above and below
/// (where there are rows) and left and right (columns wrap around).
pub fn neighbours(k: usize, height: usize, width: usize) -> impl Iterator<Item = usize> {
    let (i, j) = (k / width, k % width);
    [
        (i > 0).then(|| k - width),
        (i + 1 < height).then(|| k + width),
        Some(i * width + (j + width - 1) % width),
        Some(i * width + (j + 1) % width),
    ]
    .into_iter()
    .flatten()
}

/// Steps (4-neighbour, columns wrapping around) from every pixel to the nearest pixel
/// with a return: 0 on a return, `u32::MAX` when the image has none.
pub fn distance_to_returns(observed: &[f32], height: usize, width: usize) -> Vec<u32> {
    let mut distance = vec![u32::MAX; observed.len()];
    if observed.len() != height * width || width == 0 {
        return distance;
    }
    let mut queue = VecDeque::new();
    for (k, &d) in observed.iter().enumerate() {
        if d > 0.0 {
            distance[k] = 0;
            queue.push_back(k);
        }
    }
    while let Some(k) = queue.pop_front() {
        let next = distance[k] + 1;
        for q in neighbours(k, height, width) {
            if distance[q] > next {
                distance[q] = next;
                queue.push_back(q);
            }
        }
    }
    distance
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distance_counts_steps_and_wraps_around_the_columns() {
        // 2 x 5, one return at (0, 0).
        let mut observed = vec![0.0; 10];
        observed[0] = 5.0;
        let d = distance_to_returns(&observed, 2, 5);
        assert_eq!(d, vec![0, 1, 2, 2, 1, 1, 2, 3, 3, 2]);
        assert!(
            distance_to_returns(&[0.0; 4], 2, 2)
                .iter()
                .all(|&d| d == u32::MAX)
        );
    }
}

//! Host vectors <-> burn float tensors, and the shape operations several networks share.

use burn::tensor::{Device, Tensor, TensorData};

/// Host vector -> float tensor of the given shape.
pub fn tensor_from<const D: usize>(
    values: Vec<f32>,
    shape: [usize; D],
    device: &Device,
) -> Tensor<D> {
    Tensor::from_data(TensorData::new(values, shape), device)
}

/// Float tensor -> host vector (row-major).
pub fn tensor_to_vec<const D: usize>(x: Tensor<D>) -> Vec<f32> {
    x.into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .unwrap_or_default()
}

/// Nearest-neighbour 2x upsampling: each pixel repeated into a 2 x 2 block.
///
/// # Shapes
/// - x: `[batch, ch, H, W]` -> `[batch, ch, 2H, 2W]`
pub fn upsample_nearest(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    x.reshape([b, c, h, 1, w, 1])
        .repeat_dim(3, 2)
        .repeat_dim(5, 2)
        .reshape([b, c, 2 * h, 2 * w])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn upsample_repeats_each_pixel() {
        let device = Device::flex();
        let x = tensor_from(vec![1.0, 2.0, 3.0, 4.0], [1, 1, 2, 2], &device);
        let y = tensor_to_vec(upsample_nearest(x));
        assert_eq!(
            y,
            vec![
                1.0, 1.0, 2.0, 2.0, 1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0, 3.0, 3.0, 4.0, 4.0
            ]
        );
    }
}

//! Host vectors <-> burn float tensors.

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
